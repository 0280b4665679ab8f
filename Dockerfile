# The twohr project image: the library, every service and the CLI. Each service runs as its own
# container from this one image (see docker-compose.yml), which keeps builds small.
# Users: `docker compose up --build` (BASE_IMAGE defaults to the official python:3.11-slim).
# Hosts that cannot pull images: scripts/docker-here.sh builds a local Debian base instead.
# No model weights are baked in: they come from the /models mount or `twohr models fetch`.
# Few instructions on purpose: under the vfs storage driver every step copies the whole tree.
ARG BASE_IMAGE=python:3.11-slim

# ---- build stage: a virtual environment in /opt/twohr -------------------------------------------
FROM ${BASE_IMAGE} AS build
# docker/pip-cert/ may hold ca-certificates.crt, a CA bundle for hosts behind a TLS proxy. It goes
# into the venv's own pip.conf for this stage only and is removed before the runtime copy.
COPY pyproject.toml docker/pip-cert/ /src/
# Dependencies get their own layer, so a code change rebuilds in seconds.
RUN python3 -m venv /opt/twohr \
    && if [ -s /src/ca-certificates.crt ]; then \
         printf '[global]\ncert = /src/ca-certificates.crt\n' > /opt/twohr/pip.conf; fi \
    && /opt/twohr/bin/python -c "import tomllib; print('\n'.join(tomllib.load(open('/src/pyproject.toml', 'rb'))['project']['dependencies']))" > /src/requirements.txt \
    && PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 /opt/twohr/bin/pip install -q -r /src/requirements.txt
COPY . /src/
RUN PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 /opt/twohr/bin/pip install -q --no-deps /src \
    && /opt/twohr/bin/pip uninstall -q -y pip setuptools && rm -f /opt/twohr/pip.conf

# ---- runtime stage -------------------------------------------------------------------------------
FROM ${BASE_IMAGE}
ENV PYTHONUNBUFFERED=1 PATH=/opt/twohr/bin:$PATH MPLCONFIGDIR=/tmp/matplotlib \
    TWOHR_MODEL_MIRROR=/models TWOHR_CACHE=/cache TWOHR_ZENOH_ROUTER=tcp/router:7447
RUN useradd --create-home --uid 10001 twohr && mkdir -p /cache /recordings /data /models /run/twohr \
    && chown twohr /cache /recordings /run/twohr
COPY --from=build /opt/twohr /opt/twohr
USER twohr
CMD ["twohr", "--help"]
