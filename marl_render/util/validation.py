"""Argument checks shared by the public API.

Every check raises before anything is written, so a rejected call leaves state
unchanged. Messages name the argument, what was expected and what was given.
"""
from __future__ import annotations

import math
import os
import stat
from collections.abc import Sequence

import numpy as np
import torch

FLOAT_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


def describe(value) -> str:
    """Short description of a value for error messages."""
    if isinstance(value, torch.Tensor):
        return f"tensor of shape {tuple(value.shape)}, dtype {value.dtype}, device {value.device}"
    if isinstance(value, np.ndarray):
        return f"array of shape {value.shape}, dtype {value.dtype}"
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def unpicklable(what: str, rebuild: str) -> TypeError:
    """The error for pickling (or copying) an object that owns GL state: it says what to do instead."""
    return TypeError(f"{what} cannot be pickled or copied: it owns an OpenGL renderer, whose GL state lives in "
                     f"this process. Build it where it is needed from its configuration instead: send the "
                     f"name and keyword arguments (or functools.partial({rebuild}, ...)) to the worker and call "
                     f"{rebuild}(...) there")


def as_tensor(name: str, value, *, dtype_kind: str = "float", device=None) -> torch.Tensor:
    """Turn lists / numpy arrays / tensors into a tensor without silently changing kind.
    Tensors come back detached from autograd.

    dtype_kind: "float" accepts any float tensor (or int/float lists), "bool" accepts bool,
    "int" accepts integer tensors.
    """
    if isinstance(value, torch.Tensor):
        tensor = value.detach()  # what the library keeps must not hold the caller's autograd graph
    elif isinstance(value, (np.ndarray, list, tuple, int, float, bool, np.generic)):
        try:
            array = np.asarray(value)
            if any(stride < 0 for stride in array.strides):  # a reversed view: torch takes no negative strides
                array = array.copy()
            tensor = torch.as_tensor(array)
        except (TypeError, ValueError, RuntimeError) as exc:  # RuntimeError: tensors that require grad
            raise TypeError(f"{name} must be array-like of numbers, got {describe(value)}") from exc
    else:
        raise TypeError(f"{name} must be a torch.Tensor or array-like, got {type(value).__name__}")
    if device is not None and tensor.device != torch.device(device):
        raise ValueError(f"{name} must be on device {torch.device(device)}, got {tensor.device}")
    if dtype_kind == "float":
        if tensor.dtype == torch.bool or tensor.is_complex():
            raise TypeError(f"{name} must have a floating dtype, got {tensor.dtype}")
        if not tensor.is_floating_point():
            tensor = tensor.to(torch.float32)
    elif dtype_kind == "bool":
        if tensor.dtype != torch.bool:
            raise TypeError(f"{name} must have dtype torch.bool, got {tensor.dtype}")
    elif dtype_kind == "int":
        if tensor.is_floating_point() or tensor.dtype == torch.bool or tensor.is_complex():
            raise TypeError(f"{name} must have an integer dtype, got {tensor.dtype}")
    return tensor


def check_shape(name: str, tensor: torch.Tensor, expected: Sequence[int | None]) -> None:
    """None in `expected` matches any size."""
    shape = tuple(tensor.shape)
    ok = len(shape) == len(expected) and all(e is None or e == s for e, s in zip(expected, shape, strict=True))
    if not ok:
        want = "[" + ", ".join("*" if e is None else str(e) for e in expected) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(shape)}")


def check_host(name: str, tensor: torch.Tensor) -> None:
    """A dense tensor in host memory: the scene and the renderer pack on the CPU."""
    if tensor.device.type != "cpu":
        raise ValueError(f"{name} must be a CPU tensor (the renderer packs on the host), got device {tensor.device}")
    if tensor.layout != torch.strided:
        raise TypeError(f"{name} must be a dense (strided) tensor, got layout {tensor.layout}")


def check_finite(name: str, tensor: torch.Tensor) -> None:
    if not tensor.is_floating_point():
        return
    # A NaN or an infinity makes the sum non-finite, so a finite sum proves every value finite
    # in two ops (torch.isfinite is six on CPU); a sum that overflowed is checked in full.
    if math.isfinite(tensor.sum(dtype=torch.float64).item()):
        return
    if not bool(torch.isfinite(tensor).all()):
        bad = (~torch.isfinite(tensor)).nonzero()[0].tolist()
        raise ValueError(f"{name} must be finite (no NaN/Inf), got a non-finite value at index {bad}")


def check_range(name: str, tensor: torch.Tensor, low=None, high=None) -> None:
    if low is not None and bool((tensor < low).any()):
        raise ValueError(f"{name} must be >= {low}, got minimum {tensor.min().item()}")
    if high is not None and bool((tensor > high).any()):
        raise ValueError(f"{name} must be <= {high}, got maximum {tensor.max().item()}")


FLOAT32_MAX = float(torch.finfo(torch.float32).max)
REWARD_WEIGHT_LIMIT = 1e6  # a reward weight above this could overflow float32 rewards once multiplied
COUNT_LIMIT = 10 ** 9  # step counts and delays of a task's keywords (they meet int64 tensors and products)


def positive_int(name: str, value, *, minimum: int = 1, maximum: int | None = None) -> int:
    want = f"an int >= {minimum}" if maximum is None else f"an int in [{minimum}, {maximum}]"
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be {want}, got {describe(value)}")
    if value < minimum or maximum is not None and value > maximum:
        raise ValueError(f"{name} must be {want}, got {value}")
    return int(value)


def finite_float(name: str, value) -> float:
    """A real number (not a bool, not a string) that is finite, as a float."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TypeError(f"{name} must be a number, got {describe(value)}")
    value = float(value)
    if not np.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value}")
    return value


def positive_float(name: str, value, *, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TypeError(f"{name} must be a number, got {describe(value)}")
    value = float(value)
    if not np.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be a finite number {bound}, got {value}")
    return value


def reward_weight(name: str, value, *, allow_zero: bool = False) -> float:
    """A task's reward weight: finite, > 0 (or >= 0), and at most REWARD_WEIGHT_LIMIT, so that the
    rewards it scales stay finite in float32 (a weight of 1e39 is already infinite there)."""
    value = positive_float(name, value, allow_zero=allow_zero)
    if value > REWARD_WEIGHT_LIMIT:
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be a number {bound} and <= {REWARD_WEIGHT_LIMIT:g} (a reward weight: larger "
                         f"ones overflow float32 rewards), got {value!r}")
    return value


def resolution_hw(value, *, name: str = "resolution", max_size: int | None = None) -> tuple[int, int]:
    """int R -> (R, R); (H, Wpx) -> (H, Wpx). Both sides must be >= 1 (and <= max_size)."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        hw = (int(value), int(value))
    elif isinstance(value, (tuple, list)) and len(value) == 2 and all(
        isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in value
    ):
        hw = (int(value[0]), int(value[1]))
    else:
        raise TypeError(f"{name} must be an int or a pair of ints (height, width), got {describe(value)}")
    if min(hw) < 1:
        raise ValueError(f"{name} must be >= 1 pixel on each side, got {hw}")
    if max_size is not None and max(hw) > max_size:
        raise ValueError(f"{name} must be at most {max_size} pixels on each side (GL limit), got {hw}")
    return hw


def boolean(name: str, value) -> bool:
    """True or False only: bool("no") is True, so strings and numbers are refused."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a bool, got {describe(value)}")
    return bool(value)


_FILE_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
               (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket"))


def regular_file(name: str, value, *, kind: str) -> str:
    """The path of an existing regular file, as a str; `kind` ("model", "image") words the errors.

    Devices, pipes and directories are refused before anything opens them (reading a pipe
    could block for ever, /dev/zero never ends)."""
    if not isinstance(value, (str, os.PathLike)):
        raise TypeError(f"{name} must be a {kind} file path (str or os.PathLike), got {describe(value)}")
    path = os.fspath(value)
    if not isinstance(path, str):
        raise TypeError(f"{name} must be a {kind} file path given as str, got bytes {path!r}")
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise FileNotFoundError(f"{name}: {kind} file {path!r} does not exist") from None
    except OSError as error:
        raise ValueError(f"{name}: {kind} file {path!r} cannot be read ({error.strerror})") from None
    except ValueError:  # os.stat refuses NUL characters
        raise ValueError(f"{name} must be a {kind} file path without NUL characters, got {path!r}") from None
    if not stat.S_ISREG(mode):
        what = next((text for test, text in _FILE_KINDS if test(mode)), "something else")
        raise ValueError(f"{name} must be a regular {kind} file, got {path!r}, which is {what}")
    return path


def torch_device(name: str, value) -> torch.device:
    """A CPU or CUDA torch.device that exists here, from a str or torch.device."""
    if not isinstance(value, (str, torch.device)):
        raise TypeError(f"{name} must be a str or torch.device (e.g. 'cpu', 'cuda:0'), got {describe(value)}")
    try:
        dev = torch.device(value)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"{name} must name a torch device (e.g. 'cpu', 'cuda:0'), got {value!r}") from exc
    if dev.type == "cpu":  # torch has one CPU device; tensors made on 'cpu:0' report plain 'cpu'
        if dev.index not in (None, 0):
            raise ValueError(f"{name} must be 'cpu' (torch has a single CPU device) or a CUDA device, got {value!r}")
        return torch.device("cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{name} {value!r} was asked for but torch sees no CUDA device; use device='cpu'")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{name} must be a CPU or CUDA device (e.g. 'cpu', 'cuda:0'), got {value!r}")
    if dev.type == "cuda" and (dev.index or 0) >= torch.cuda.device_count():
        raise ValueError(f"{name} {value!r} was asked for but torch sees {torch.cuda.device_count()} CUDA device(s)")
    return dev
