"""Test support: a package must not import certain others (design §2: agents never import the
world; the live view's observer never needs it either)."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def check_imports(folder: Path, modules: tuple[str, ...], forbidden: tuple[str, ...]) -> None:
    """Fail if a ``.py`` file under ``folder`` imports a ``forbidden`` top-level package (a
    static check), or if importing ``modules`` in a fresh interpreter loads one of them."""
    for path in folder.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for name in names:
                assert name.split(".")[0] not in forbidden, f"{path.name} imports {name}"
    code = (f"import sys, {', '.join(modules)}; "
            f"bad = [m for m in {forbidden!r} if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
