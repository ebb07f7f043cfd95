"""Import rules of the package layout (README "Architecture"), checked on the source text.

- A method package (``wsim.bem``, ``wsim.eol``, ``wsim.pbd``) never imports another method's
  package or another method's kernels: what two methods share lives in a shared module.
- Shared modules (``wsim/*.py``, ``wsim.mesh``) import no method package; only ``wsim/__init__.py``
  (the public API) gathers them.
- A kernel module imports only kernels of its own method or shared kernels.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("bem", "eol", "pbd")


def _kernel_method(module: str) -> str | None:
    """The method a ``wsim.kernels.<name>`` module belongs to (by its file-name prefix), else None."""
    name = module.split(".")[2] if module.count(".") >= 2 else ""
    return next((m for m in METHODS if name == m or name.startswith(m + "_")), None)


def _owner(module: str) -> str | None:
    """The method a module belongs to, or None for a shared module."""
    parts = module.split(".")
    if len(parts) >= 2 and parts[0] == "wsim" and parts[1] in METHODS:
        return parts[1]
    if module.startswith("wsim.kernels."):
        return _kernel_method(module)
    return None


def _imports(path: Path, module: str) -> list[str]:
    """Absolute names of the wsim modules ``path`` imports (``from wsim import bem`` counts as wsim.bem)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = module.split(".")[: -node.level]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.append(name)
            out += [f"{name}.{a.name}" for a in node.names]  # ``from wsim import bem``
    return [n for n in out if n == "wsim" or n.startswith("wsim.")]


def _modules() -> list[tuple[Path, str]]:
    mods = []
    for path in sorted((ROOT / "wsim").rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        mods.append((path, ".".join(rel.parts).removesuffix(".__init__")))
    for path in sorted((ROOT / "kernels").glob("*.py")):
        mods.append((path, "wsim.kernels." + path.stem if path.stem != "__init__" else "wsim.kernels"))
    return mods


def _violations() -> list[str]:
    bad = []
    for path, module in _modules():
        if module == "wsim":  # the public API gathers every method
            continue
        mine = _owner(module)
        for name in _imports(path, module):
            theirs = _owner(name)
            if theirs is not None and theirs != mine:
                who = f"method '{mine}'" if mine else "shared module"
                bad.append(f"{path.relative_to(ROOT)} ({who}) imports {name} (method '{theirs}')")
    return bad


def test_no_method_imports_another_method() -> None:
    bad = _violations()
    assert not bad, "imports across method packages:\n" + "\n".join(bad)


def test_the_scan_sees_a_violation(tmp_path: Path) -> None:
    # the scan must be able to fail: a made-up EoL module importing BEM and PBD code is caught
    src = "from wsim.bem.frame import rodrigues\nfrom wsim import pbd\nfrom wsim.kernels import bem_step\n"
    (tmp_path / "x.py").write_text(src)
    names = _imports(tmp_path / "x.py", "wsim.eol.x")
    owners = {_owner(n) for n in names} - {None}
    assert owners == {"bem", "pbd"}
    assert _owner("wsim.kernels.eol_grid") == "eol" and _owner("wsim.rigid") is None


@pytest.mark.parametrize("package", METHODS)
def test_method_packages_exist(package: str) -> None:
    assert (ROOT / "wsim" / package / "__init__.py").is_file()
