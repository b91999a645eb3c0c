"""The exported controller from Python, through ctypes (for checks and closed loops).

:class:`ExportedController` builds the shared library of an exported project
(``make -C DIR shared``) and calls its API (``lfm_controller.h``) on NumPy arrays, so the
controller a robot would run can be driven by the project's environments and compared with
the Python agent.
"""

from __future__ import annotations

import ctypes
import re
import subprocess
from pathlib import Path
from typing import Any

import numpy as np

_DEFINE = re.compile(r"^#define (LFM_\w+) (\S+)", re.MULTILINE)


class LfmInfo(ctypes.Structure):
    """``lfm_info`` of lfm_controller.h."""

    _fields_ = [
        ("status", ctypes.c_int),
        ("success", ctypes.c_int),
        ("usable", ctypes.c_int),
        ("action", ctypes.c_int),
        ("iterations", ctypes.c_long),
        ("objective", ctypes.c_double),
        ("slack", ctypes.c_double),
        ("solve_time", ctypes.c_double),
        ("step_time", ctypes.c_double),
        ("filter_resets", ctypes.c_long),
    ]


ACTIONS = ("plan", "previous_plan", "fallback")


def config_defines(folder: str | Path) -> dict[str, Any]:
    """The ``#define``s of an export's ``lfm_config.h`` (numbers as ints or floats)."""
    text = (Path(folder) / "lfm_config.h").read_text(encoding="utf-8")
    out: dict[str, Any] = {}
    for key, value in _DEFINE.findall(text):
        if value.startswith('"'):
            out[key] = value.strip('"')
        else:
            try:
                out[key] = int(value)
            except ValueError:
                out[key] = float(value)
    return out


def build_shared(folder: str | Path, cc: str | None = None) -> Path:
    """``make -C folder shared`` (with ``CC=cc`` if given): the shared library's path.

    Raises:
        RuntimeError: with make's last lines when the build fails.
    """
    folder = Path(folder)
    cmd = ["make", "-C", str(folder), "shared"] + ([f"CC={cc}"] if cc else [])
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-5:]
        raise RuntimeError(f"make shared failed in {folder}: {tail}")
    return folder / "liblfm_controller.so"


def _nm(*args: str) -> set[str]:
    done = subprocess.run(["nm", *args], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"nm {' '.join(args)}: {done.stderr.strip()[:200]}")
    return {line.split()[-1].split("@")[0] for line in done.stdout.splitlines() if line.split()}


def external_dependencies(folder: str | Path) -> dict[str, Any]:
    """What a built export needs at run time: the shared libraries ``ldd`` lists for
    ``example``, and the symbols the static library leaves undefined that neither it nor
    libc and libm define (``nm``).

    Returns:
        ``{"libraries": [...], "other_libraries": [...] (not libc, libm, the loader or the
        vDSO), "undefined": [...], "outside_libc_libm": [...], "ok": bool}``.

    Raises:
        RuntimeError: when ``ldd`` or ``nm`` fails (not built, tools missing).
    """
    folder = Path(folder)
    done = subprocess.run(
        ["ldd", str(folder / "example")], capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise RuntimeError(f"ldd {folder / 'example'}: {done.stderr.strip()[:200]}")
    libraries = sorted({line.split()[0] for line in done.stdout.splitlines() if line.strip()})
    basic = ("linux-vdso.so", "libc.so", "libm.so", "ld-linux", "/lib64/ld-linux")
    other = [lib for lib in libraries if not lib.startswith(basic)]
    archive = str(folder / "liblfm_controller.a")
    undefined = _nm("-u", archive) - _nm("--defined-only", archive)
    system: set[str] = set()
    for line in done.stdout.splitlines():
        if "=>" in line and ("libc.so" in line or "libm.so" in line):
            system |= _nm("-D", "--defined-only", line.split("=>")[1].split()[0])
    outside = sorted(undefined - system)
    return {
        "libraries": libraries,
        "other_libraries": other,
        "undefined": sorted(undefined),
        "outside_libc_libm": outside,
        "ok": not other and not outside,
    }


def run_make(folder: str | Path, *targets: str, cc: str | None = None) -> float:
    """``make -C folder [targets]`` (with ``CC=cc``): its wall time [s].

    Raises:
        RuntimeError: with make's last lines when the build fails.
    """
    import time

    cmd = ["make", "-C", str(folder), *targets] + ([f"CC={cc}"] if cc else [])
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-5:]
        raise RuntimeError(f"make {' '.join(targets)} failed in {folder}: {tail}")
    return time.perf_counter() - t0


def _array(
    value: Any, shape: tuple[int, ...], name: str, finite: bool = True, also: Any = None
) -> np.ndarray:
    """``value`` as a C-contiguous float64 array of exactly ``shape`` (or ``also``), finite.

    Raises:
        ValueError: naming ``name`` and the expected shape, or the non-finite entry.
    """
    a = np.ascontiguousarray(value, dtype=float)
    if a.shape != shape and (also is None or a.shape != tuple(also)):
        other = "" if also is None else f" or {tuple(also)}"
        raise ValueError(f"{name}: shape {a.shape}, expected {shape}{other}")
    if finite and not np.all(np.isfinite(a)):
        index = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"{name}{list(index)} = {a[index]}: every entry must be finite")
    return a


class ExportedController:
    """The exported controller of ``folder`` (built with :func:`build_shared` if needed).

    Args:
        folder: an ``lfm-export`` project.
        rebuild: build the shared library even if it is there.
    """

    def __init__(self, folder: str | Path, rebuild: bool = False) -> None:
        self.folder = Path(folder)
        path = self.folder / "liblfm_controller.so"
        if rebuild or not path.is_file():
            path = build_shared(self.folder)
        d = config_defines(self.folder)
        self.nx, self.nu, self.nw = d["LFM_NX"], d["LFM_NU"], d["LFM_NW"]
        self.np, self.ng, self.horizon, self.n_scenarios = (
            d["LFM_NP"],
            d["LFM_NG"],
            d["LFM_N"],
            d["LFM_NS"],
        )
        self.step_available = bool(d["LFM_STEP_AVAILABLE"])
        self.agent, self.system = d["LFM_AGENT"], d["LFM_SYSTEM"]
        lib = self.lib = ctypes.CDLL(str(path.resolve()))
        P = ctypes.c_void_p
        lib.lfm_controller_new.restype = P
        lib.lfm_controller_free.argtypes = [P]
        lib.lfm_controller_reset.argtypes = [P, ctypes.c_uint64]
        lib.lfm_controller_step.argtypes = [P, P, P]
        lib.lfm_controller_solve.argtypes = [P, P, P, P]
        lib.lfm_controller_last_problem.argtypes = [P, P, P, P]
        lib.lfm_controller_estimate.argtypes = [P, P, P]
        lib.lfm_controller_info.argtypes = [P]
        lib.lfm_controller_info.restype = LfmInfo
        lib.lfm_status_name.argtypes = [ctypes.c_int]
        lib.lfm_status_name.restype = ctypes.c_char_p
        self._ptr = lib.lfm_controller_new()
        if not self._ptr:
            raise MemoryError("lfm_controller_new: out of memory")
        self._u = np.zeros(self.nu)

    def __del__(self) -> None:
        ptr, self._ptr = getattr(self, "_ptr", None), None
        if ptr:
            self.lib.lfm_controller_free(ptr)

    def reset(self, seed: int = 0) -> None:
        """A new episode (``lfm_controller_reset``)."""
        self.lib.lfm_controller_reset(self._ptr, int(seed) & (2**64 - 1))

    def step(self, y: Any) -> tuple[np.ndarray, str]:
        """The input for the measurement ``y`` ``(nx,)`` and the solve's status name (a
        NaN or infinite ``y`` is the controller's to handle: ``"Bad_Input"`` and the
        fallback input, as on the robot).

        Raises:
            ValueError: for a ``y`` of another shape.
        """
        y = _array(y, (self.nx,), "y", finite=False)
        u = np.zeros(self.nu)
        code = self.lib.lfm_controller_step(self._ptr, y.ctypes.data, u.ctypes.data)
        return u, self.status_name(code)

    def solve(self, x0: Any, W: Any) -> tuple[np.ndarray, str]:
        """The plan ``(N, nu)`` for ``x0`` ``(nx,)`` and ``W`` ``(Ns, N, nw)`` (or
        ``(Ns, N)`` when ``nw`` is 1), and the status name.

        Raises:
            ValueError: naming the expected shape, for ``x0`` or ``W`` of another shape (a
                transposed ``W`` included), or a NaN or infinite number in them.
        """
        x0 = _array(x0, (self.nx,), "x0")
        shape = (self.n_scenarios, self.horizon, self.nw)
        W = _array(W, shape, "W", also=shape[:2] if self.nw == 1 else None).reshape(shape)
        plan = np.zeros((self.horizon, self.nu))
        code = self.lib.lfm_controller_solve(
            self._ptr, x0.ctypes.data, W.ctypes.data, plan.ctypes.data
        )
        return plan, self.status_name(code)

    def last_problem(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the last step solved: ``x0`` ``(Ns, nx)``, ``W`` ``(Ns, N, nw)``, the back-off
        ``(N, ng)``."""
        x0 = np.zeros((self.n_scenarios, self.nx))
        W = np.zeros((self.n_scenarios, self.horizon, self.nw))
        b = np.zeros((self.horizon, max(self.ng, 1)))
        self.lib.lfm_controller_last_problem(
            self._ptr, x0.ctypes.data, W.ctypes.data, b.ctypes.data
        )
        return x0, W, b[:, : self.ng]

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """The estimate's mean ``(nx + p,)`` and covariance."""
        d = self.nx + self.np
        mean, cov = np.zeros(d), np.zeros((d, d))
        self.lib.lfm_controller_estimate(self._ptr, mean.ctypes.data, cov.ctypes.data)
        return mean, cov

    def info(self) -> dict[str, Any]:
        """The last step's record (``lfm_info``), the action as a name."""
        raw = self.lib.lfm_controller_info(self._ptr)
        out = {name: getattr(raw, name) for name, _ in LfmInfo._fields_}
        out["status"] = self.status_name(raw.status)
        out["success"] = bool(raw.success)
        out["usable"] = bool(raw.usable)
        out["action"] = ACTIONS[raw.action] if 0 <= raw.action < len(ACTIONS) else "?"
        return out

    def status_name(self, code: int) -> str:
        return self.lib.lfm_status_name(int(code)).decode()


__all__ = [
    "ACTIONS",
    "ExportedController",
    "LfmInfo",
    "build_shared",
    "config_defines",
    "external_dependencies",
    "run_make",
]
