# RepNet lifting service: HTTP (FastAPI) and gRPC on onnxruntime, the bundled model inside.
#
#   docker build -t repnet .
#   docker run --rm -p 8000:8000 -p 50051:50051 repnet
#
# BASE_IMAGE must be a Debian-like image with Python 3.11 as `python3` (with venv/ensurepip);
# deploy/test-container.sh builds on a local debootstrap image this way.
ARG BASE_IMAGE=python:3.11-slim

# ---- build: a virtual environment holding the service and its runtime dependencies ----
FROM ${BASE_IMAGE} AS build
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1
RUN python3 -m venv /opt/repnet
WORKDIR /src
# Dependencies first (their own layer): the plain install's and the `server` extra's, read from
# pyproject.toml so there is one list (the extra's own "repnet[local]" stands for the local extra).
COPY pyproject.toml ./
RUN python3 -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; \
x = p['optional-dependencies']; print('\n'.join(d for d in p['dependencies'] + x['server'] + x['local'] \
if not d.startswith('repnet')))" > /tmp/requirements.txt \
    && /opt/repnet/bin/pip install -r /tmp/requirements.txt
# The package is built from service/ (repnet) and training/ (repnet.train, which the wheel holds) by the
# project's build backend (deploy/packaging, pyproject.toml's build-system); the
# server never imports training, so repnet/train is taken out of the image again (no torch here).
COPY README.md LICENSE ./
COPY deploy/packaging ./deploy/packaging
COPY service ./service
COPY training ./training
RUN test -f service/models/repnet-h36m.onnx \
    && /opt/repnet/bin/pip install --no-deps . \
    && rm -rf /opt/repnet/lib/python3*/site-packages/repnet/train \
    && cd / && /opt/repnet/bin/python -c "import importlib.resources as r, repnet, repnet.server.app; \
assert '/opt/repnet/' in repnet.__file__; \
assert r.files('repnet').joinpath('models/repnet-h36m.onnx').is_file()" \
    && /opt/repnet/bin/pip uninstall -y pip setuptools wheel

# ---- runtime: the interpreter from the base image, the venv, a non-root user; no compilers ----
FROM ${BASE_IMAGE} AS runtime
LABEL org.opencontainers.image.title="repnet" \
      org.opencontainers.image.description="RepNet 2D-to-3D human pose lifting service (HTTP + gRPC)" \
      org.opencontainers.image.licenses="Apache-2.0"
RUN groupadd --gid 10001 repnet \
    && useradd --uid 10001 --gid 10001 --no-create-home --home-dir /nonexistent --shell /usr/sbin/nologin repnet
COPY --from=build /opt/repnet /opt/repnet
# ORT_DISABLE_TELEMETRY: onnxruntime >= 1.29 sends usage telemetry on Linux unless told not to.
# REPNET_HOST: the service binds 127.0.0.1 by default (a workstation's `make serve` stays private);
# in a container that is the container's own loopback, which published ports never reach.
ENV PATH=/opt/repnet/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    REPNET_HOST=0.0.0.0 \
    REPNET_HTTP_PORT=8000 \
    REPNET_GRPC_PORT=50051 \
    ORT_DISABLE_TELEMETRY=1
USER 10001:10001
EXPOSE 8000 50051
# No curl in slim images: the venv's Python asks /readyz (200 once the model is loaded).
HEALTHCHECK --interval=10s --timeout=3s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/readyz' % os.environ.get('REPNET_HTTP_PORT', '8000'), timeout=2)"]
STOPSIGNAL SIGTERM
CMD ["python", "-m", "repnet", "serve"]
