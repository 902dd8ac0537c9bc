"""Reading torch files of unknown origin: residual weights, property-model weights and recorded cube tosses.

Each is loaded with ``weights_only=True`` (no code runs on load) and every tensor is checked to be plain data
(`tensor_problem`) before numpy or a network reads it: torch loads sparse, nested, meta, quantized and complex
tensors safely, but the first four then fail with a traceback wherever they are used, and a complex tensor copied
into a real network or array loses its imaginary part with only a warning.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from grounder.errors import GrounderError


@contextmanager
def quiet_pickle_protocol_warning() -> Iterator[None]:
    """Around ``torch.load(..., weights_only=True)`` of an untrusted file: silences the two-line UserWarning torch
    prints for a pickle protocol other than its own (a plain pickle, not a ``torch.save`` file), just before it
    fails on such a file; the caller's one-line error says all there is to say."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Detected pickle protocol", category=UserWarning)
        yield


def load_weights_file(path: Path, remedy: str) -> Any:
    """``torch.load`` of an untrusted weights file (``weights_only=True``, on the CPU), without torch's warnings.

    Args:
        path: The file.
        remedy: What the user should do when it is not a weights file (the end of the error line).

    Raises:
        GrounderError: one line, ``"{path}: not a valid weights file (<error type>); {remedy}"``. Not torch's own
            text: it runs over several lines and suggests ``weights_only=False``, unsafe for a file of unknown origin.
    """
    import torch

    try:
        with quiet_pickle_protocol_warning():
            return torch.load(path, weights_only=True, map_location="cpu")
    except Exception as exc:  # torch raises many types for corrupt or unsafe files
        raise GrounderError(f"{path}: not a valid weights file ({type(exc).__name__}); {remedy}") from exc


def tensor_problem(tensor: object) -> str | None:
    """What keeps a loaded value from being read as a dense array of real numbers on the CPU, for an error line
    ("is a sparse tensor, ..."), or None. Integer and bool tensors pass: callers that need floating point say so.
    """
    import torch

    if not isinstance(tensor, torch.Tensor):
        return f"is a {type(tensor).__name__}, not a tensor"
    kind = (
        "nested" if tensor.is_nested else
        "sparse" if tensor.layout != torch.strided else
        "meta (no data)" if tensor.is_meta else
        "quantized" if tensor.is_quantized else
        "complex" if tensor.is_complex() else
        None
    )  # fmt: skip
    if kind is not None:
        return f"is a {kind} tensor, not a dense real one"
    if tensor.device.type != "cpu":  # map_location="cpu" moves what it can; a custom device type stays
        return f"is on device {tensor.device.type}, not the CPU"
    if not (tensor.dtype.is_floating_point or tensor.dtype in _integer_dtypes()):  # bits16, uint1, float4, ...
        return f"has dtype {tensor.dtype}, which holds no numbers to read"
    return None


@functools.cache
def _integer_dtypes() -> frozenset[Any]:
    import torch

    names = ("bool", "uint8", "int8", "int16", "int32", "int64", "uint16", "uint32", "uint64")
    return frozenset(getattr(torch, name) for name in names if hasattr(torch, name))
