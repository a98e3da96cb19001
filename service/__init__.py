"""repnet: RepNet 2D-to-3D human pose lifting, as a service and its clients.

What users call (the light install, `pip install repnet`, has all of it):

    import repnet
    with repnet.LiftClient("http://localhost:8000") as client:
        result = client.lift(keypoints)          # (17, 2) px -> repnet.LiftResult
    with repnet.StreamClient("localhost:50051") as stream:
        for answer in stream.stream(frames):  # arrays or repnet.Frame in, repnet.FrameResult out
            ...

The server (`repnet serve`) needs `pip install 'repnet[server]'`; `repnet lift --local` needs
`repnet[local]`; training and `repnet adapt` need `repnet[train]`.
"""

# This folder is the source of `repnet`, the only name an install gives it (pyproject.toml's
# package-dir). Python run from the checkout's root would also find it under the folder's own name,
# a second copy of every module beside the installed one: refused, with the name to use.
if __name__ != "repnet":
    raise ImportError(
        f"{__name__!r} is the source folder of the package repnet: import repnet (pip install -e .)"
    )


from repnet.client.http import AsyncLiftClient, LiftClient
from repnet.client.result import LiftClientError, LiftInputError, LiftResult
from repnet.client.stream import Frame, FrameResult, Person, PersonResult, StreamClient
from repnet.core.version import VERSION

__version__ = VERSION

__all__ = [
    "AsyncLiftClient",
    "Frame",
    "FrameResult",
    "LiftClient",
    "LiftClientError",
    "LiftInputError",
    "LiftResult",
    "Person",
    "PersonResult",
    "StreamClient",
    "__version__",
]
