"""Every Python code block of the README runs (issue 19, point 7), so the examples cannot rot.

Blocks run in a fresh namespace each, in a temporary folder (they write USD and checkpoints), on
the CPU. A block whose sizes are for a GPU or a long run gets the smaller values of ``SHRINK``
(text substitutions, each of which must apply: a README edit that removes one fails here, so
the table follows the README); everything else runs as printed.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCKS = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)

# (a line of the block that identifies it, [(text, CI replacement), ...])
SHRINK: list[tuple[str, list[tuple[str, str]]]] = [
    ("cube = wsim.mesh.bumpy_cube(size=0.45, divisions=10, amplitude=0.04)",
     [("divisions=10", "divisions=3"), ("world.run(frames=60,", "world.run(frames=3,")]),
    ("world.run(frames=30, out=\"bem_constraints.usda\")", [("world.run(frames=30,", "world.run(frames=3,")]),
    ("world.run(30, out=\"eol_ball.usda\")", [("resolution=12", "resolution=6"), ("world.run(30,", "world.run(2,")]),
    ("cube = mesh.bumpy_cube(size=0.45, divisions=22)", [("divisions=22", "divisions=3")]),
    ("summary = world.run(frames=90, out=\"out.usda\")", [("world.run(frames=90,", "world.run(frames=5,")]),
]


def _shrunk(block: str) -> str:
    for marker, subs in SHRINK:
        if marker in block:
            for old, new in subs:
                assert old in block, f"README block changed: '{old}' is gone (update SHRINK in {__file__})"
                block = block.replace(old, new)
    return block


def test_every_shrink_rule_finds_its_block() -> None:
    for marker, _ in SHRINK:
        assert any(marker in b for b in BLOCKS), f"no README block holds '{marker}' any more"


@pytest.mark.parametrize("k", range(len(BLOCKS)), ids=[f"block{k}" for k in range(len(BLOCKS))])
def test_readme_block_runs(k: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("WSIM_CACHE_DIR", str(tmp_path / "cache"))
    code = _shrunk(BLOCKS[k]).replace("device=None", "device=\"cpu\"")
    code = re.sub(r"wsim\.World\(fps=(\d+)\)", r'wsim.World(fps=\1, device="cpu")', code)
    exec(compile(code, f"README block {k}", "exec"), {"__name__": "readme_block"})
