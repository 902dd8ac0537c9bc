"""The public API: every name `grounder`, `reconstruction` and `scene_export` offer resolves, importing `grounder` stays
cheap, and README's Python snippet matches the API it shows (its imports exist, its calls fit their signatures).

The snippet itself grounds a scene and calibrates 40 tosses (minutes); the figures it would produce are tested where
each stage is. Here it is read, not run: a renamed function, a moved name or a dropped keyword fails the test.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("package", ["grounder", "reconstruction", "scene_export", "image2sim_common"])
def test_every_public_name_resolves(package: str) -> None:
    module = importlib.import_module(package)
    missing = [name for name in module.__all__ if not hasattr(module, name)]
    assert missing == []


def test_each_stage_offers_options_function_result() -> None:
    import grounder

    for options, function, result in [
        ("GroundOptions", "ground", "GroundResult"),
        ("CalibrateOptions", "calibrate", "CalibrationResult"),
        ("DiagnoseOptions", "diagnose", "Diagnosis"),
        ("TrackOptions", "track", "TrackResult"),
        ("InteractionOptions", "ground_with_interaction", "InteractionResult"),
    ]:
        assert callable(getattr(grounder, function))
        assert inspect.isclass(getattr(grounder, options)) and inspect.isclass(getattr(grounder, result))


def test_importing_grounder_loads_no_heavy_library() -> None:
    # cv2 is not among them: `reconstruction` loads it first on purpose (before any pycolmap: see its __init__)
    heavy = ("torch", "pycolmap", "open3d", "trimesh", "coacd", "ray", "matplotlib")
    code = f"import sys, grounder, grounder.cli; print([m for m in {heavy!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert out.stdout.strip() == "[]", out.stdout


def _readme_python() -> str:
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), re.S)
    assert len(blocks) == 1, "README shows one Python snippet"
    return blocks[0]


def test_readme_snippet_imports_exist_and_calls_fit_their_signatures() -> None:
    tree = ast.parse(_readme_python())
    names: dict[str, object] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = importlib.import_module(node.module or "")
            for alias in node.names:
                assert hasattr(module, alias.name), f"README imports {alias.name} from {node.module}: not there"
                names[alias.asname or alias.name] = getattr(module, alias.name)
    assert {"ground", "calibrate", "reconstruct", "GroundOptions", "CalibrateOptions"} <= set(names)
    checked = 0
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in names:
            target = names[node.func.id]
            signature = inspect.signature(target)
            args = [None] * len(node.args)  # the values do not matter, only their number and names
            kwargs = {kw.arg: None for kw in node.keywords if kw.arg is not None}
            try:
                signature.bind(*args, **kwargs)
            except TypeError as exc:
                pytest.fail(f"README calls {node.func.id}({ast.unparse(node)[:80]}...): {exc}")
            checked += 1
    assert checked >= 8  # every call in the snippet: reconstruct, ground, calibrate, simulate, diagnose_files, ...
