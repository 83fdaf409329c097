"""Builds and loads the native CPU kernels (csrc/: compositing and projection) on first use.

The extension is compiled with ``torch.utils.cpp_extension.load`` into a per-user cache folder, keyed by a hash of
the source, its folder, the flags, torch's version and the machine, so it is built once per machine and checkout
and never inside an isolated pip build environment (which would pull a multi-GB CUDA torch). Set ``AGG_EXT_DIR``
to move the cache.

torch marks a build in progress with a ``lock`` file in the build folder and waits, without a timeout, for it to
go. A process killed while building (a cancelled job's work horse is SIGKILLed) leaves that file behind, and
every later first render on the machine waited forever. So builds are also serialised with ``fcntl.flock`` on
``build.flock``, which the kernel releases when its holder dies: whoever holds it is the only builder, and a
``lock`` file found then is stale and removed. Two checkouts shared one folder before the source folder was in
the key; each switch rebuilt (ninja's build file names the sources' paths).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import platform
import shutil
import sys
import threading
from pathlib import Path
from types import ModuleType

import torch

CSRC = Path(__file__).with_name("csrc")
SOURCES = [CSRC / "rasterize.cpp", CSRC / "project.cpp", CSRC / "bindings.cpp"]
# -ffp-contract=off: no fused multiply-adds, so the kernel evaluates sigma exactly like the torch reference.
CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-std=c++17"]
_lock = threading.Lock()
_module: ModuleType | None = None


class NativeBuildError(RuntimeError):
    """The native CPU kernels could not be built (usually: no C++ compiler)."""


def _arch_flags() -> list[str]:
    # -march=native is safe because the build is cached per machine (the hash includes the CPU model).
    if platform.machine() in ("x86_64", "AMD64", "aarch64", "arm64") and os.environ.get("AGG_NATIVE_ARCH", "1") == "1":
        return ["-march=native"]
    return []


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("model name", "flags", "Features")):
                return line
    except OSError:
        pass
    return platform.processor()


def cache_dir() -> Path:
    flags = CFLAGS + _arch_flags()
    key = hashlib.sha256(
        b"".join(src.read_bytes() for src in SOURCES) + " ".join(flags).encode() + torch.__version__.encode()
        + sys.version.encode() + _cpu_model().encode() + str(CSRC.resolve()).encode()
    ).hexdigest()[:16]
    root = Path(os.environ.get("AGG_EXT_DIR", Path.home() / ".cache" / "agg" / "ext"))
    return root / f"render_{key}"


def load() -> ModuleType:
    """Compile (once per machine) and import the extension. Raises NativeBuildError with the reason."""
    global _module
    if _module is not None:
        return _module
    with _lock:
        if _module is not None:
            return _module
        compiler = os.environ.get("CXX", "c++")
        if shutil.which(compiler) is None:
            raise NativeBuildError(
                f"no C++ compiler found ({compiler!r} is not on PATH): the 'cpu' render backend compiles its "
                "kernels on first use. Install one (e.g. `apt-get install g++`) or use backend='torch'."
            )
        from torch.utils.cpp_extension import load as load_ext

        build_dir = cache_dir()
        build_dir.mkdir(parents=True, exist_ok=True)
        flags = CFLAGS + _arch_flags()
        with open(build_dir / "build.flock", "a") as guard:
            fcntl.flock(guard, fcntl.LOCK_EX)  # released by the kernel if this process dies (module doc)
            try:
                (build_dir / "lock").unlink(missing_ok=True)  # torch's baton: stale, nobody else builds now
                _module = load_ext(
                    name="agg_render_cpu",
                    sources=[str(src) for src in SOURCES],
                    extra_cflags=flags,
                    extra_ldflags=["-fopenmp"],
                    build_directory=str(build_dir),
                    verbose=False,
                )
            except Exception as exc:  # compiler errors surface as RuntimeError / subprocess errors
                raise NativeBuildError(f"building the native CPU kernels in {build_dir} failed: {exc}") from exc
            finally:
                fcntl.flock(guard, fcntl.LOCK_UN)
        return _module
