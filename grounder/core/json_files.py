"""Reading a JSON file the user handed us (a scene's ``scene.json``, a marker layout, a model's metadata).

Such a file may be hand-edited, truncated or someone else's: every way it can fail to parse becomes one line naming
the file, what is wrong and what to do, and a key given twice in one object is refused rather than kept last-wins
(Python's ``json`` silently keeps the last, so which value the writer meant cannot be told).
"""

import json
from pathlib import Path
from typing import Any

from grounder.errors import GrounderError, shown


class _RepeatedKey(Exception):
    """A JSON object names the same key twice (args: the key)."""


def _without_repeated_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``json.loads``'s ``object_pairs_hook``: the object as a dict, or `_RepeatedKey` for a key given twice."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _RepeatedKey(key)
        out[key] = value
    return out


def read_json_file(path: Path, remedy: str, error: type[GrounderError] = GrounderError) -> Any:
    """The parsed content of a JSON file (UTF-8), or ``error`` with one line ending in ``remedy``.

    Args:
        path: The file.
        remedy: What the user can do, appended to every message (e.g. "re-run `image2sim ground` for this scene").
        error: The `GrounderError` subclass to raise.

    Raises:
        error: the file cannot be read, is not UTF-8, is not JSON, is nested deeper than the parser allows, or
            gives a key twice in one object.
    """
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"), object_pairs_hook=_without_repeated_keys)
    except _RepeatedKey as exc:
        raise error(f"{path}: key {shown(exc.args[0])} appears twice in one object; {remedy}") from exc
    except OSError as exc:
        raise error(f"{path}: could not be read ({exc.strerror or type(exc).__name__}); {remedy}") from exc
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte {exc.start}); {remedy}") from exc
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc.msg}, line {exc.lineno}); {remedy}") from exc
    except RecursionError as exc:
        raise error(f"{path}: JSON nested too deeply (more levels than a parser allows); {remedy}") from exc
