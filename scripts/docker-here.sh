#!/usr/bin/env bash
# A Docker engine and the twohr image, on this host, whatever it has.
#
#   scripts/docker-here.sh run CMD [ARG...]   engine + image, run CMD, then stop the engine if we started it
#   scripts/docker-here.sh up                 engine + image, and leave the engine running
#   scripts/docker-here.sh down               stop the engine that `up` started
#
# Steps, each skipped when it is not needed:
#   1. no engine answers: install Debian's docker.io, docker-compose and debootstrap (as root) and
#      start `dockerd --storage-driver=D --iptables=false --bridge=none` in the background, D being
#      overlay2 where this kernel mounts an overlay on Docker's disk (a probe mount), else vfs
#      (TWOHR_DOCKER_STORAGE=vfs|overlay2 chooses);
#   2. the official python:3.11-slim base cannot be pulled: build twohr-base:bookworm with
#      debootstrap from the apt mirror and `docker import` it;
#   3. build twohr:latest from the Dockerfile, trusting the host's CA bundle (the one the host's pip
#      uses, else the system one) for hosts that reach PyPI through a TLS proxy.
# CMD sees TWOHR_COMPOSE (the compose command with its -f files: docker-compose.host.yml in place
# of docker-compose.override.yml when the engine has no bridge network) and TWOHR_BASE_IMAGE, and
# COMPOSE_HTTP_TIMEOUT (default 600 s: under vfs, creating a container copies the whole image).
# When no engine can be started the script prints one "SKIP" line and exits 0, so CI stays green
# on hosts without Docker; any later failure is an error.
set -euo pipefail
cd "$(dirname "$0")/.."

STATE=runs/docker
mkdir -p "$STATE"
log() { echo "docker-here: $*" >&2; }
skip() { echo "SKIP compose: $* (no Docker engine, nothing run)"; exit 0; }

engine_answers() { timeout 10 docker info >/dev/null 2>&1; }

start_engine() {
    if engine_answers; then log "a Docker engine answers; using it"; return; fi
    [ "$(id -u)" = 0 ] || skip "no engine answers and this user cannot install one (not root)"
    if ! command -v dockerd >/dev/null || ! command -v docker-compose >/dev/null \
            || ! command -v debootstrap >/dev/null; then
        log "installing docker.io docker-compose debootstrap"
        export DEBIAN_FRONTEND=noninteractive
        apt-get install -y -q docker.io docker-compose debootstrap >"$STATE/apt.log" 2>&1 \
            || { apt-get update -q >>"$STATE/apt.log" 2>&1 \
                 && apt-get install -y -q docker.io docker-compose debootstrap >>"$STATE/apt.log" 2>&1; } \
            || skip "apt-get could not install docker.io (see $STATE/apt.log)"
    fi
    command -v docker >/dev/null || skip "no docker client after installing docker.io"
    local driver
    for driver in $(storage_drivers); do
        log "starting dockerd ($driver storage, no bridge); log in $STATE/dockerd.log"
        dockerd --storage-driver="$driver" --iptables=false --bridge=none >"$STATE/dockerd.log" 2>&1 &
        echo $! >"$STATE/dockerd.pid"
        for i in $(seq 60); do
            engine_answers && { log "engine up after ${i} s"; return; }
            kill -0 "$(cat "$STATE/dockerd.pid")" 2>/dev/null || break
            sleep 1
        done
        log "dockerd with $driver storage did not answer (see $STATE/dockerd.log)"
        stop_engine
    done
    skip "dockerd did not answer within 60 s (see $STATE/dockerd.log)"
}

# overlay2 first where the kernel mounts an overlay on the disk that holds Docker's data: vfs works
# anywhere but copies the whole image (about 1.2 GB) into every container it creates.
storage_drivers() {
    if [ -n "${TWOHR_DOCKER_STORAGE:-}" ]; then echo "$TWOHR_DOCKER_STORAGE"; return; fi
    local probe=/var/lib/docker/twohr-overlay-probe
    rm -rf "$probe" && mkdir -p "$probe"/{lower,upper,work,merged}
    if mount -t overlay overlay -o "lowerdir=$probe/lower,upperdir=$probe/upper,workdir=$probe/work" \
            "$probe/merged" 2>/dev/null; then
        umount "$probe/merged"; echo "overlay2 vfs"
    else
        echo vfs
    fi
    rm -rf "$probe"
}

stop_engine() {
    [ -f "$STATE/dockerd.pid" ] || return 0
    local pid; pid=$(cat "$STATE/dockerd.pid"); rm -f "$STATE/dockerd.pid"
    kill -0 "$pid" 2>/dev/null || return 0
    log "stopping the dockerd this script started (pid $pid)"
    kill -TERM "$pid"
    for _ in $(seq 60); do kill -0 "$pid" 2>/dev/null || return 0; sleep 1; done
    log "dockerd did not stop in 60 s; killing it"; kill -KILL "$pid" 2>/dev/null || true
}

compose_command() {
    local files="-f docker-compose.yml -f docker-compose.override.yml"
    docker network inspect bridge >/dev/null 2>&1 || files="-f docker-compose.yml -f docker-compose.host.yml"
    if docker compose version >/dev/null 2>&1; then echo "docker compose $files"
    elif command -v docker-compose >/dev/null; then echo "docker-compose $files"
    else echo "no compose command: install docker-compose or the compose plugin" >&2; return 1; fi
}

apt_mirror() {
    local uri
    uri=$(grep -hoE '^(URIs:|deb) +[^ ]+' /etc/apt/sources.list.d/*.sources /etc/apt/sources.list 2>/dev/null \
          | awk '{print $2}' | grep -vE 'security|cloud.google|nodesource' | head -1 || true)
    echo "${uri:-http://deb.debian.org/debian}"
}

base_image() {
    if [ -n "${TWOHR_BASE_IMAGE:-}" ]; then echo "$TWOHR_BASE_IMAGE"; return; fi
    local official=python:3.11-slim local=twohr-base:bookworm
    if docker image inspect "$official" >/dev/null 2>&1 || timeout 30 docker pull -q "$official" >/dev/null 2>&1; then
        echo "$official"; return
    fi
    if ! docker image inspect "$local" >/dev/null 2>&1; then
        local rootfs="$STATE/rootfs" mirror t0=$SECONDS; mirror=$(apt_mirror)
        log "cannot pull $official; building $local with debootstrap from $mirror (about 40 s)"
        rm -rf "$rootfs"
        debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates \
            bookworm "$rootfs" "$mirror" >"$STATE/debootstrap.log" 2>&1 \
            || { log "debootstrap failed, see $STATE/debootstrap.log"; return 1; }
        rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/* "$rootfs"/usr/share/doc \
               "$rootfs"/usr/share/man "$rootfs"/usr/share/locale "$rootfs"/var/cache/apt/*.bin
        tar -C "$rootfs" -c . | docker import - "$local" >/dev/null
        rm -rf "$rootfs"
        log "built $local in $((SECONDS - t0)) s"
    fi
    echo "$local"
}

build_image() {
    # the bundle the host's pip trusts, else the system bundle: harmless where PyPI is reached directly
    local cert=${PIP_CERT:-${SSL_CERT_FILE:-${REQUESTS_CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}}}
    rm -f docker/pip-cert/ca-certificates.crt
    if [ -n "$cert" ] && [ -s "$cert" ]; then
        log "the image build trusts the host's CA bundle $cert"
        cp "$cert" docker/pip-cert/ca-certificates.crt
    fi
    local t0=$SECONDS
    log "building twohr:latest on $TWOHR_BASE_IMAGE; log in $STATE/build.log"
    # shellcheck disable=SC2086
    $TWOHR_COMPOSE build >"$STATE/build.log" 2>&1 || { tail -30 "$STATE/build.log" >&2; return 1; }
    local size; size=$(docker image inspect twohr:latest --format '{{.Size}}')
    log "built twohr:latest in $((SECONDS - t0)) s, $((size / 1000000)) MB"
    printf '{"build_s": %d, "image_bytes": %d, "base_image": "%s"}\n' $((SECONDS - t0)) "$size" \
        "$TWOHR_BASE_IMAGE" >"$STATE/build.json"
}

up() {
    export COMPOSE_HTTP_TIMEOUT=${COMPOSE_HTTP_TIMEOUT:-600} DOCKER_CLIENT_TIMEOUT=${DOCKER_CLIENT_TIMEOUT:-600}
    start_engine
    TWOHR_BASE_IMAGE=$(base_image); export TWOHR_BASE_IMAGE
    TWOHR_COMPOSE=$(compose_command); export TWOHR_COMPOSE
    build_image
}

case "${1:-}" in
    up) up; log "engine left running; compose with: $TWOHR_COMPOSE" ;;
    down) stop_engine ;;
    run)
        shift; [ $# -gt 0 ] || { echo "usage: $0 run CMD [ARG...]" >&2; exit 2; }
        trap stop_engine EXIT
        up
        "$@" ;;
    *) awk 'NR > 1 && !/^#/ {exit} NR > 1' "$0" | sed 's/^# \{0,1\}//'; [ "${1:-}" = -h ] || [ "${1:-}" = --help ]; exit ;;
esac
