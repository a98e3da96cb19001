#!/usr/bin/env bash
# Build the Dockerfile with podman on a local Debian bookworm base image, run it, and check it for real:
# readiness, POST /lift, gRPC health and Lift, /metrics, the image HEALTHCHECK, then SIGTERM -> exit 0.
#
# No Docker engine and no image registry are needed: the base image is made here with debootstrap
# (Debian's mirror) and `podman import`, and cached in $REPNET_CACHE_DIR so a later run skips that.
# Needs root (apt, debootstrap, rootful podman). Usage: deploy/test-container.sh
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
CACHE_DIR=${REPNET_CACHE_DIR:-/var/cache/repnet}
SUITE=bookworm
MIRROR=${REPNET_DEBIAN_MIRROR:-http://deb.debian.org/debian}
BASE_PACKAGES=python3.11,python3-venv,python3-pip,ca-certificates
# The base image's tag names what went into it, so a change (packages, CA certificates) makes a new one.
BASE_KEY=$(printf '%s %s %s' "$SUITE" "$BASE_PACKAGES" "$(cat /usr/local/share/ca-certificates/*.crt 2>/dev/null)" \
    | sha256sum | cut -c1-12)
BASE_IMAGE=localhost/repnet-base:$SUITE-$BASE_KEY
IMAGE=${REPNET_IMAGE:-localhost/repnet:test}
NAME=repnet-container-test-$$
WORK=$(mktemp -d)
# The host-side checks (smoke.py) need grpc and httpx: the project's .venv when there is one.
if [[ -z ${PYTHON:-} && -x $ROOT/.venv/bin/python ]]; then PYTHON=$ROOT/.venv/bin/python; fi
PYTHON=${PYTHON:-python3}

# crun cannot set rlimits in this sandbox, and podman's default rlimits (nofile 1048576) are above the
# hard limits here, which cannot be raised without CAP_SYS_RESOURCE: use runc and explicit limits no
# higher than this shell's (nproc also under podman's own 32768, or runc fails with "rlimit type 6").
NOFILE=$(ulimit -Hn); [[ $NOFILE == unlimited || $NOFILE -gt 65536 ]] && NOFILE=65536
NPROC=$(ulimit -Hu); [[ $NPROC == unlimited || $NPROC -gt 16384 ]] && NPROC=16384
PODMAN=(podman --runtime runc)
LIMITS=(--ulimit "nofile=$NOFILE:$NOFILE" --ulimit "nproc=$NPROC:$NPROC")

log() { printf '[test-container %s] %s\n' "$(date +%H:%M:%S)" "$*"; }
fail() { log "FAIL: $*"; exit 1; }

ensure_tools() {
    local missing=()
    for tool in podman runc debootstrap; do command -v "$tool" >/dev/null || missing+=("$tool"); done
    if ((${#missing[@]})); then
        log "installing ${missing[*]} (apt)"
        apt-get update -q
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
            podman runc debootstrap uidmap fuse-overlayfs slirp4netns conmon containernetworking-plugins
    fi
}

# The base image: debootstrap minbase + Python 3.11 + this machine's extra CA certificates (so pip
# inside the build trusts a TLS-intercepting proxy where there is one). Cached as a rootfs tarball, so a
# later run that lost the podman image re-imports it in seconds instead of running debootstrap again.
ensure_base_image() {
    if "${PODMAN[@]}" image exists "$BASE_IMAGE"; then
        log "base image $BASE_IMAGE present"
        return
    fi
    local tarball=$CACHE_DIR/repnet-base-$SUITE-$BASE_KEY.tar
    if [[ ! -s $tarball ]]; then
        local rootfs
        rootfs=$(mktemp -d /var/tmp/repnet-rootfs.XXXXXX)
        log "debootstrap $SUITE (minbase + $BASE_PACKAGES) into $rootfs"
        nice -n 10 debootstrap --variant=minbase --include="$BASE_PACKAGES" "$SUITE" "$rootfs" "$MIRROR" \
            >"$rootfs.log" 2>&1 || { tail -20 "$rootfs.log"; fail "debootstrap"; }
        if compgen -G '/usr/local/share/ca-certificates/*.crt' >/dev/null; then
            cp /usr/local/share/ca-certificates/*.crt "$rootfs/usr/local/share/ca-certificates/"
            chroot "$rootfs" update-ca-certificates >/dev/null
        fi
        rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
        mkdir -p "$CACHE_DIR"
        tar -C "$rootfs" --numeric-owner -cf "$tarball.tmp" . && mv "$tarball.tmp" "$tarball"
        rm -rf "$rootfs" "$rootfs.log"
    else
        log "base rootfs cached: $tarball"
    fi
    "${PODMAN[@]}" import --change 'CMD ["/usr/bin/python3"]' "$tarball" "$BASE_IMAGE" >/dev/null
    "${PODMAN[@]}" run --rm "${LIMITS[@]}" "$BASE_IMAGE" python3 --version
}

free_port() { "$PYTHON" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

cleanup() {
    local rc=$?
    if "${PODMAN[@]}" container exists "$NAME" 2>/dev/null; then
        ((rc == 0)) || { log "container logs:"; "${PODMAN[@]}" logs "$NAME" 2>&1 | tail -40 || true; }
        "${PODMAN[@]}" rm -f "$NAME" >/dev/null 2>&1 || true
    fi
    rm -rf "$WORK"
    exit "$rc"
}
trap cleanup EXIT

"$PYTHON" -c 'import grpc, grpc_health, httpx' 2>/dev/null \
    || fail "$PYTHON cannot import grpc, grpc_health and httpx, which deploy/smoke.py needs: run \
\`make container-test\` (it installs the service into .venv) or set PYTHON to a Python that has them"
[[ $(id -u) == 0 ]] || fail "needs root (rootful podman, debootstrap)"
[[ -f $ROOT/service/models/repnet-h36m.onnx ]] || fail "service/models/repnet-h36m.onnx is missing"
ensure_tools
ensure_base_image

log "building $IMAGE (BASE_IMAGE=$BASE_IMAGE)"
start=$SECONDS
nice -n 5 "${PODMAN[@]}" build --format docker --network host "${LIMITS[@]}" \
    --build-arg "BASE_IMAGE=$BASE_IMAGE" -t "$IMAGE" "$ROOT"
log "built in $((SECONDS - start)) s; size $("${PODMAN[@]}" image inspect "$IMAGE" --format '{{.Size}}') bytes"

log "checking the runtime image: non-root, no torch, no compiler"
user=$("${PODMAN[@]}" image inspect "$IMAGE" --format '{{.Config.User}}')
[[ -n $user && ${user%%:*} != 0 && ${user%%:*} != root ]] || fail "image runs as root (User='$user')"
"${PODMAN[@]}" run --rm "${LIMITS[@]}" --no-healthcheck --network none "$IMAGE" sh -c \
    'test "$(id -u)" != 0 && ! command -v gcc && ! command -v cc && ! python -c "import torch" 2>/dev/null' \
    || fail "runtime image has root, a compiler or torch"

HTTP_PORT=$(free_port)
GRPC_PORT=$(free_port)
# As deploy/k8s/base/deployment.yaml runs it: read-only root, /tmp writable, no capabilities, 2 CPUs, 1 GiB.
log "starting $NAME (HTTP $HTTP_PORT, gRPC $GRPC_PORT, --network host, read-only, 2 CPUs, 1 GiB)"
"${PODMAN[@]}" run -d --name "$NAME" --network host "${LIMITS[@]}" --health-interval disable \
    --read-only --tmpfs /tmp --cap-drop ALL --security-opt no-new-privileges --cpus 2 --memory 1g \
    -e REPNET_HTTP_PORT="$HTTP_PORT" -e REPNET_GRPC_PORT="$GRPC_PORT" -e REPNET_HOST=127.0.0.1 \
    -e REPNET_INTRA_OP_THREADS=1 "$IMAGE" >/dev/null 2>"$WORK/podman-run.err" \
    || { cat "$WORK/podman-run.err"; fail "podman run"; }

log "waiting for /readyz"
for _ in $(seq 120); do
    "$PYTHON" -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:$HTTP_PORT/readyz', timeout=2)" \
        2>/dev/null && break
    [[ $("${PODMAN[@]}" inspect "$NAME" --format '{{.State.Running}}') == true ]] || fail "container exited early"
    sleep 0.5
done
"${PODMAN[@]}" healthcheck run "$NAME" >/dev/null 2>&1 || fail "image HEALTHCHECK (python -> /readyz) unhealthy"
log "ready; HEALTHCHECK healthy"

log "smoke checks: POST /lift, gRPC health + Lift, /metrics"
PYTHONPATH=$ROOT "$PYTHON" "$ROOT/deploy/smoke.py" --http "http://127.0.0.1:$HTTP_PORT" \
    --grpc "127.0.0.1:$GRPC_PORT" || fail "smoke checks"

log "SIGTERM -> expecting a clean exit (code 0)"
start=$SECONDS
"${PODMAN[@]}" kill --signal TERM "$NAME" >/dev/null
code=$(timeout 60 "${PODMAN[@]}" wait "$NAME") || fail "container did not stop within 60 s of SIGTERM"
[[ $code == 0 ]] || fail "exit code $code after SIGTERM"
log "exited 0 after $((SECONDS - start)) s"
# Keep the layer cache of recent builds, drop untagged images older than a day.
"${PODMAN[@]}" image prune -f --filter until=24h >/dev/null 2>&1 || true
log "PASS"
