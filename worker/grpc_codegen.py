"""Python code for ``proto/agg/v1/*.proto``, generated with grpcio-tools at build time or first use.

Generated code is never committed or edited: ``ensure_generated()`` compiles the protos into ``worker/_gen/``
(git-ignored) when that folder is missing or stale, and ``scripts/gen_proto.py`` does the same from the command
line (a Docker build runs it). A stamp file holds the SHA-256 of the ``.proto`` sources and the grpcio-tools
version, so an edited proto or a new grpcio-tools regenerates on the next import.

protoc writes ``from agg.v1 import common_pb2``, which would resolve to the engine package ``agg``; those imports
are rewritten to relative ones (``from . import common_pb2``), so the modules form the flat package
``worker._gen`` while the descriptors keep their proto names (``agg/v1/render.proto``, ``agg.v1.RenderService``),
which is what reflection and other-language clients see. Generation writes into a temporary folder next to the
target and renames it into place under a file lock (in the temp folder), so concurrent processes never import half-written modules.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import shutil
import tempfile
from pathlib import Path

PROTO_ROOT = Path(os.environ.get("AGG_PROTO_DIR", Path(__file__).resolve().parents[1] / "proto"))
GEN_DIR = Path(__file__).resolve().parent / "_gen"
PROTO_FILES = ("common", "job", "scene", "render")  # proto/agg/v1/<name>.proto
STAMP = "STAMP"
_IMPORT = re.compile(r"^from agg\.v1 import (\w+_pb2)", re.MULTILINE)


def _fingerprint(proto_root: Path) -> str:
    import grpc_tools

    h = hashlib.sha256()
    for name in PROTO_FILES:
        h.update((proto_root / "agg" / "v1" / f"{name}.proto").read_bytes())
    h.update(getattr(grpc_tools, "__version__", "").encode())
    try:
        from importlib.metadata import version

        h.update(version("grpcio-tools").encode())
    except Exception:  # noqa: BLE001  (an unusual install without metadata: the sources alone decide)
        pass
    return h.hexdigest()


def is_current(gen_dir: Path = GEN_DIR, proto_root: Path = PROTO_ROOT) -> bool:
    stamp = gen_dir / STAMP
    return stamp.is_file() and stamp.read_text().strip() == _fingerprint(proto_root)


def generate(gen_dir: Path = GEN_DIR, proto_root: Path = PROTO_ROOT) -> Path:
    """Compile the protos into ``gen_dir`` (replacing it); returns ``gen_dir``."""
    from grpc_tools import protoc

    gen_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="._gen_", dir=gen_dir.parent))
    try:
        include = Path(protoc.__file__).resolve().parent / "_proto"  # google/protobuf/*.proto
        sources = [str(proto_root / "agg" / "v1" / f"{n}.proto") for n in PROTO_FILES]
        args = ["grpc_tools.protoc", f"-I{proto_root}", f"-I{include}", f"--python_out={tmp}",
                f"--pyi_out={tmp}", f"--grpc_python_out={tmp}", *sources]
        if protoc.main(args) != 0:
            raise RuntimeError(f"protoc failed on {sources}")
        out = tmp / "agg" / "v1"
        for f in sorted(out.iterdir()):
            if f.suffix in (".py", ".pyi"):
                (tmp / f.name).write_text(_IMPORT.sub(r"from . import \1", f.read_text()))
        shutil.rmtree(tmp / "agg")
        (tmp / "__init__.py").write_text('"""Generated from proto/agg/v1 by worker/grpc_codegen.py; do not edit."""\n')
        (tmp / STAMP).write_text(_fingerprint(proto_root) + "\n")
        old = gen_dir.with_name(gen_dir.name + f".old{os.getpid()}")
        if gen_dir.exists():
            gen_dir.rename(old)
        tmp.rename(gen_dir)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return gen_dir


def ensure_generated(gen_dir: Path = GEN_DIR, proto_root: Path = PROTO_ROOT) -> Path:
    """Generate the modules unless they are current (cheap when they are: one hash of four small files)."""
    if not (proto_root / "agg" / "v1").is_dir():
        if (gen_dir / STAMP).is_file():  # an installed copy without the proto sources: use what was built
            return gen_dir
        raise FileNotFoundError(f"no protos at {proto_root}/agg/v1 (set AGG_PROTO_DIR)")
    if is_current(gen_dir, proto_root):
        return gen_dir
    gen_dir.parent.mkdir(parents=True, exist_ok=True)
    key = hashlib.sha256(str(gen_dir).encode()).hexdigest()[:16]
    with open(Path(tempfile.gettempdir()) / f"agg-grpc-gen-{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not is_current(gen_dir, proto_root):  # (a process that already imported them keeps its copy)
                generate(gen_dir, proto_root)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return gen_dir
