# The machine daemon and the Rider in one image; compose.yaml runs it twice (docs/deploy.md).
# Two targets: `machine` (the default, the last stage: daemon, Rider, operator UI, RevPi
# backend) and `gateway` (the same plus the plant gateway's OPC UA and Prometheus libraries).
#
#   docker build -t localhost/ride-machine:0.1.0 .
#   podman build --format docker -t localhost/ride-machine:0.1.0 .   # docker format keeps HEALTHCHECK
#   docker build --target gateway -t localhost/ride-machine-gateway:0.1.0 .
#   docker run --rm localhost/ride-machine:0.1.0                     # the supervised simulator
#   docker run --rm localhost/ride-machine:0.1.0 rider --help        # the Rider CLI / operator UI
#
# Nothing here needs BuildKit (no RUN --mount, no `# syntax=` line): Debian 12's docker 20.10 and
# docker-compose 1.29 build it with the classic builder, BuildKit and podman (buildah) alike, and
# no frontend image is fetched from a registry on an offline site.
# Behind a private index or a TLS-intercepting proxy, give pip its settings from outside
# (docs/deploy.md): --build-arg PIP_INDEX_URL=…, or docker/pip/pip.conf and docker/pip/ca.crt.

# Fully qualified, so podman resolves it without a registries.conf alias.
ARG PYTHON_IMAGE=docker.io/library/python:3.11-slim

# ---------------------------------------------------------------------------------- builder
# Every dependency of the machine's image at its locked version (requirements/machine.txt,
# hashes checked) and the package itself, installed in the virtualenv /opt/venv: the one thing
# a runtime stage takes from here.
FROM ${PYTHON_IMAGE} AS builder

# Empty defaults: no "missing build argument" warnings; an empty one is not passed to pip.
ARG PIP_INDEX_URL=""
ARG PIP_EXTRA_INDEX_URL=""
ARG PIP_TRUSTED_HOST=""
# armv7 (32-bit RevPi OS) has no wheels for some dependencies: 1 installs a compiler for them.
ARG WITH_COMPILER=0
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_ROOT_USER_ACTION=ignore

WORKDIR /src
COPY requirements/machine.txt requirements/runtime.txt requirements/build.txt requirements/
# The site's pip settings, if any (docker/pip/: its README alone by default), and the build
# arguments, written to /etc/pip-build/env.sh for each pip run here (an empty one is not passed
# on). They stay in the builder stages: a runtime stage takes /opt/venv only.
COPY docker/pip/ /etc/pip-build/

# hadolint ignore=DL3008
RUN set -eu; \
    if [ "$WITH_COMPILER" = 1 ]; then \
        apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev libffi-dev \
        && rm -rf /var/lib/apt/lists/*; \
    fi; \
    { [ -z "$PIP_INDEX_URL" ] || echo "export PIP_INDEX_URL='$PIP_INDEX_URL'"; \
      [ -z "$PIP_EXTRA_INDEX_URL" ] || echo "export PIP_EXTRA_INDEX_URL='$PIP_EXTRA_INDEX_URL'"; \
      [ -z "$PIP_TRUSTED_HOST" ] || echo "export PIP_TRUSTED_HOST='$PIP_TRUSTED_HOST'"; \
      [ ! -f /etc/pip-build/pip.conf ] || echo "export PIP_CONFIG_FILE=/etc/pip-build/pip.conf"; \
      [ ! -f /etc/pip-build/ca.crt ] || echo "export PIP_CERT=/etc/pip-build/ca.crt"; \
    } > /etc/pip-build/env.sh; \
    unset PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_TRUSTED_HOST; \
    . /etc/pip-build/env.sh; \
    python -m venv --without-pip /opt/venv; \
    pip --python /opt/venv/bin/python install --require-hashes --no-deps -r requirements/machine.txt; \
    pip install --require-hashes --no-deps -r requirements/build.txt

COPY pyproject.toml README.md ./
COPY schema/ schema/
COPY common/ common/
COPY hal/ hal/
COPY service/ service/
COPY sim/ sim/
COPY rider/ rider/
# The package itself, offline: its dependencies are all in /opt/venv already.
RUN pip wheel --no-deps --no-build-isolation --no-index --wheel-dir /tmp/wheel . \
    && pip --python /opt/venv/bin/python install --no-deps --no-index /tmp/wheel/*.whl

# The plant gateway's libraries on top (requirements/runtime.txt: the machine's pins and
# asyncua, cryptography, prometheus_client and theirs), for the `gateway` target only.
FROM builder AS builder-gateway
# The site's pip settings as the builder wrote them (/etc/pip-build/env.sh).
RUN set -eu; \
    . /etc/pip-build/env.sh; \
    pip --python /opt/venv/bin/python install --require-hashes --no-deps -r requirements/runtime.txt

# ---------------------------------------------------------------------------------- runtime
# What both images share: the base, the user, the default files, the healthcheck.
FROM ${PYTHON_IMAGE} AS runtime

# The package's version (pyproject.toml; tests/deploy/test_static.py checks it) and OCI labels.
ARG VERSION=0.1.0
LABEL org.opencontainers.image.title="ride-machine" \
      org.opencontainers.image.description="PLC-style machine daemon for a two-axis ride, with its Rider, over Zenoh" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.licenses="Apache-2.0" \
      org.opencontainers.image.base.name="docker.io/library/python:3.11-slim"

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PATH=/opt/venv/bin:$PATH \
    MACHINE_HEARTBEAT_FILE=/dev/shm/machine.heartbeat

# A regular (not --system) account: uid 10001 is outside the system range, and useradd warns.
RUN groupadd --gid 10001 machine \
    && useradd --uid 10001 --gid 10001 --no-log-init --no-create-home \
        --home-dir /var/lib/machine --shell /usr/sbin/nologin machine \
    && mkdir -p /etc/machine /var/lib/machine \
    && chown 10001:10001 /var/lib/machine

# Defaults only: compose mounts the site's own files over these.
COPY machine.toml zenoh.json5 /etc/machine/
COPY zenoh/acl.json5 zenoh/tls.json5 /etc/machine/zenoh/
# The site router (docker/compose.router.yaml): Zenoh's router mode on the machine's profile.
COPY docker/site_router.py /opt/site-router/

USER 10001:10001
WORKDIR /var/lib/machine
# Calibration and persisted parameters live in /var/lib/machine: mount a named volume there
# (compose does). No VOLUME line: it would give every container of this image, the rider's too,
# an anonymous volume that outlives it.

# Zenoh (the daemon listens, see zenoh.json5) and the operator UI (`rider ui`).
EXPOSE 7447/tcp 8080/tcp

# SIGTERM makes the daemon force every output safe first, then close its Zenoh session and
# exit 0 (`event=stopped code=0 outputs=safe`); a SIGKILL leaves no chance to do that in software.
STOPSIGNAL SIGTERM

# Healthy = the daemon's scan loop cycles: it touches MACHINE_HEARTBEAT_FILE (a tmpfs) about once
# a second while it does, and the check is `find`'s look at the file's age (fresh: under 6 s),
# a few milliseconds of CPU, no Python, no Zenoh session (docs/deploy.md, "The healthcheck").
# compose.yaml has the same check as a CMD-SHELL string (the form every compose implementation
# passes on intact); here in exec form, which is the same `sh -c`.
HEALTHCHECK --interval=5s --timeout=3s --start-period=30s --retries=3 \
    CMD ["/bin/sh", "-c", "find /dev/shm/machine.heartbeat -mmin -0.1 | grep -q ."]

# The daemon as a child of its supervisor (docs/supervisor.md): outputs safe and a restart
# when the daemon dies or freezes.
CMD ["machine", "supervise", "--sim", "--config", "/etc/machine/machine.toml", "--zenoh-config", "/etc/machine/zenoh.json5", "--data-dir", "/var/lib/machine"]

# ---------------------------------------------------------------------------------- gateway
# `docker build --target gateway`: the plant gateway's image (docker/compose.gateway.yaml).
FROM runtime AS gateway
COPY --from=builder-gateway /opt/venv /opt/venv

# ---------------------------------------------------------------------------------- machine
# The default target: the machine, the Rider and its UI, without the gateway's libraries.
FROM runtime AS machine
COPY --from=builder /opt/venv /opt/venv
