# The twohr project image: the library, every service and the CLI. Each service runs as its own
# container from this one image (see docker-compose.yml), which keeps builds small.
# Users: `docker compose up` (BASE_IMAGE defaults to the official python:3.11-slim).
# Hosts that cannot pull images: scripts/docker-here.sh builds a local Debian base instead.
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 \
    TWOHR_MODEL_MIRROR=/models TWOHR_CACHE=/cache TWOHR_ZENOH_ROUTER=tcp/router:7447
# Optional: a CA bundle for hosts that reach PyPI through a TLS proxy (empty for normal users).
ARG PIP_CERT=
RUN python3 -m venv /opt/twohr && /opt/twohr/bin/python -m pip install --upgrade pip
ENV PATH=/opt/twohr/bin:$PATH
WORKDIR /app
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY services ./services
RUN --mount=type=secret,id=pip_cert,required=false \
    if [ -f /run/secrets/pip_cert ]; then export PIP_CERT=/run/secrets/pip_cert; fi; \
    pip install . && useradd --create-home --uid 10001 twohr && mkdir -p /cache /recordings \
    && chown twohr /cache /recordings
USER twohr
CMD ["twohr", "--help"]
