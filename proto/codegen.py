"""Generate the committed gRPC stubs in service/_proto/ from proto/: python proto/codegen.py."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from grpc_tools import protoc

ROOT = Path(__file__).resolve().parent.parent
PROTO_DIR = ROOT / "proto"
OUT_DIR = ROOT / "service" / "_proto"
PROTOS = ["repnet/v1/lifter.proto"]
PACKAGE = "repnet._proto"


def _fix_imports(path: Path) -> None:
    """protoc writes `from repnet.v1 import x`; make it absolute within the service package."""
    text = path.read_text()
    fixed = re.sub(r"^from repnet\.v1 import", f"from {PACKAGE}.repnet.v1 import", text, flags=re.M)
    path.write_text(fixed)


def main() -> int:
    """Generate the stubs of proto/repnet/v1/lifter.proto into service/_proto; protoc's exit status."""
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    include = Path(protoc.__file__).resolve().parent / "_proto"  # google/protobuf/*.proto
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_DIR}",
        f"-I{include}",
        f"--python_out={OUT_DIR}",
        f"--pyi_out={OUT_DIR}",
        f"--grpc_python_out={OUT_DIR}",
        *(str(PROTO_DIR / p) for p in PROTOS),
    ]
    if protoc.main(args) != 0:
        print("protoc failed", file=sys.stderr)
        return 1
    for package in [
        OUT_DIR,
        *{(OUT_DIR / p).parent for p in PROTOS},
        *{(OUT_DIR / p).parent.parent for p in PROTOS},
    ]:
        (package / "__init__.py").touch()
    for generated in OUT_DIR.rglob("*_pb2*.py*"):
        _fix_imports(generated)
    print(f"wrote stubs for {', '.join(PROTOS)} to {OUT_DIR.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
