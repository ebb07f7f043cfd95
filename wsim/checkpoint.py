"""Checkpoints: a World's frame and every body's state in one HDF5 file, to resume a run.

Layout (format ``wsim-checkpoint``, version ``FORMAT_VERSION``)::

    /                    attrs: format, version, wsim_version, frame, time, scene (JSON)
    /bodies/<i>          attrs: name; one dataset per state field (``Body.get_state``)

``scene`` describes what the state means: fps, up axis, gravity, and for every body its name
and ``Body.signature()`` (class, surface hash, the settings that shape its state), and the
colliders' names and kinds. ``restore`` refuses a file whose format version or scene differs
from the World it is loaded into, naming what differs, and a file it cannot read (truncated, not
HDF5, a dataset missing) with ``CheckpointError``; either way the World is left as it was: every
body's state is checked against the file before any is changed, and a failure part-way puts
back the bodies already loaded.

Files are written atomically: a temporary file in the target folder, flushed to disk, then
renamed onto the target, so an interrupted save leaves the previous checkpoint intact.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from wsim.errors import CheckpointError
from wsim.validate import output_folder

if TYPE_CHECKING:
    from wsim.world import World

FORMAT = "wsim-checkpoint"
FORMAT_VERSION = 6  # 2: BEM and EoL states carry the coupling impulses still to deliver (issue 18); 3: and EoL the push rates of its yielding partners; 4: EoL bodies touch in one QP (no push rates); EoL signatures now carry the material and plasticity (a version-4 file of an EoL body is refused by its signature, naming them; files of other bodies still load); 5: EoL states carry the push handed to each yielding partner over the last interval (the partner yields to its change only); 6: and PBD states too (with the contacts of the last iteration on each partner)


def scene_description(world: World) -> dict[str, Any]:
    """What a checkpoint of ``world`` must match to be restored into another World."""
    return {
        "fps": world.fps,
        "up_axis": world.up_axis,
        "gravity": [float(g) for g in world.gravity],
        "bodies": [{"name": b.name, **b.signature()} for b in world.bodies],
        "colliders": [{"name": c.name, "class": type(c).__name__, "kinematic": bool(c.kinematic)}
                      for c in world.colliders],
    }


def _json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=lambda o: o.item() if isinstance(o, np.generic) else str(o))


def save(world: World, path: str | os.PathLike) -> Path:
    """Write ``world``'s frame and every body's state to ``path`` (atomically); returns the path."""
    import h5py

    import wsim

    p = Path(path).expanduser()
    folder = output_folder(p, "checkpoint")
    world._bind()
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=folder)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["version"] = FORMAT_VERSION
            f.attrs["wsim_version"] = wsim.__version__
            f.attrs["frame"] = world.frame
            f.attrs["time"] = world.time
            f.attrs["scene"] = _json(scene_description(world))
            bodies = f.create_group("bodies")
            for i, body in enumerate(world.bodies):
                g = bodies.create_group(str(i))
                g.attrs["name"] = body.name
                for key, value in body.get_state().items():
                    g.create_dataset(key, data=value)
        with open(tmp, "rb+") as fh:  # on disk before the rename makes it visible
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return p


def read(path: str | os.PathLike) -> tuple[int, dict[str, Any], list[tuple[str, dict[str, np.ndarray]]]]:
    """(frame, scene description, [(body name, state arrays)]) from a checkpoint file, all in memory."""
    import h5py

    p = Path(path).expanduser()
    if not p.is_file():
        raise CheckpointError(f"checkpoint '{p}' does not exist")
    try:
        with h5py.File(p, "r") as f:
            if f.attrs.get("format") != FORMAT:
                raise CheckpointError(f"checkpoint '{p}' is not a wsim checkpoint")
            version = int(f.attrs["version"])
            if version != FORMAT_VERSION:
                raise CheckpointError(
                    f"checkpoint '{p}' has format version {version}; this wsim ({FORMAT_VERSION}) cannot read it")
            frame = int(f.attrs["frame"])
            scene = json.loads(f.attrs["scene"])
            bodies = []
            for i in range(len(scene["bodies"])):
                g = f["bodies"][str(i)]
                bodies.append((str(g.attrs["name"]), {k: np.array(g[k]) for k in g.keys()}))
    except CheckpointError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise CheckpointError(f"checkpoint '{p}' cannot be read (truncated or damaged?): {exc}") from None
    return frame, scene, bodies


def _differences(saved: dict[str, Any], live: dict[str, Any]) -> list[str]:
    out = [f"{k}: saved {saved.get(k)!r}, this scene {live.get(k)!r}" for k in ("fps", "up_axis", "gravity")
           if _json(saved.get(k)) != _json(live.get(k))]
    names_saved = [b["name"] for b in saved.get("bodies", [])]
    names_live = [b["name"] for b in live["bodies"]]
    if names_saved != names_live:
        out.append(f"bodies: saved {names_saved}, this scene {names_live}")
    else:
        for bs, bl in zip(saved["bodies"], live["bodies"]):
            for k in sorted(set(bs) | set(bl)):
                if _json(bs.get(k)) != _json(bl.get(k)):
                    out.append(f"body '{bl['name']}' {k}: saved {bs.get(k)!r}, this scene {bl.get(k)!r}")
    if _json(saved.get("colliders")) != _json(live["colliders"]):
        out.append(f"colliders: saved {[c['name'] for c in saved.get('colliders', [])]}, "
                   f"this scene {[c['name'] for c in live['colliders']]}")
    return out


def restore(world: World, path: str | os.PathLike) -> int:
    """Load a checkpoint into ``world`` (built by the same scene script); returns its frame."""
    frame, scene, saved = read(path)
    world._bind()
    diff = _differences(scene, scene_description(world))
    if diff:
        raise CheckpointError(f"checkpoint '{path}' is from another scene: " + "; ".join(diff))
    before = [b.get_state() for b in world.bodies]
    done = []
    try:
        for body, (_, arrays) in zip(world.bodies, saved):
            body.set_state(arrays)  # checks every field before writing any
            done.append(body)
    except Exception as exc:
        for body, state in zip(done, before):
            body.set_state(state)
        if isinstance(exc, CheckpointError):
            raise
        raise CheckpointError(f"checkpoint '{path}': {exc}") from None
    world.frame = frame
    return frame
