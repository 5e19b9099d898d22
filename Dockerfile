# The machine daemon and the Rider in one image; compose.yaml runs it twice (docs/deploy.md).
#
#   docker build -t localhost/ride-machine:local .
#   podman build --format docker -t localhost/ride-machine:local .   # docker format keeps HEALTHCHECK
#   docker run --rm localhost/ride-machine:local                     # the supervised simulator
#   docker run --rm localhost/ride-machine:local rider --help        # the Rider CLI / operator UI
#
# Nothing here needs BuildKit (no RUN --mount, no `# syntax=` line): Debian 12's docker 20.10 and
# docker-compose 1.29 build it with the classic builder, BuildKit and podman (buildah) alike, and
# no frontend image is fetched from a registry on an offline site.
# Behind a private index or a TLS-intercepting proxy, give pip its settings from outside
# (docs/deploy.md): --build-arg PIP_INDEX_URL=…, or docker/pip/pip.conf and docker/pip/ca.crt.

# Fully qualified, so podman resolves it without a registries.conf alias.
ARG PYTHON_IMAGE=docker.io/library/python:3.11-slim

# ---------------------------------------------------------------------------------- builder
# Every dependency at its locked version (hashes checked) and the package itself, installed in
# the virtualenv /opt/venv: the one thing the runtime stage takes from here.
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
COPY requirements/runtime.txt requirements/build.txt requirements/
# The site's pip settings, if any (docker/pip/: its README alone by default). They stay in this
# stage: the runtime stage takes /opt/venv only.
COPY docker/pip/ /etc/pip-build/

# hadolint ignore=DL3008
RUN set -eu; \
    if [ "$WITH_COMPILER" = 1 ]; then \
        apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev libffi-dev \
        && rm -rf /var/lib/apt/lists/*; \
    fi; \
    [ -n "$PIP_INDEX_URL" ] || unset PIP_INDEX_URL; \
    [ -n "$PIP_EXTRA_INDEX_URL" ] || unset PIP_EXTRA_INDEX_URL; \
    [ -n "$PIP_TRUSTED_HOST" ] || unset PIP_TRUSTED_HOST; \
    if [ -f /etc/pip-build/pip.conf ]; then export PIP_CONFIG_FILE=/etc/pip-build/pip.conf; fi; \
    if [ -f /etc/pip-build/ca.crt ]; then export PIP_CERT=/etc/pip-build/ca.crt; fi; \
    python -m venv --without-pip /opt/venv; \
    pip --python /opt/venv/bin/python install --require-hashes --no-deps -r requirements/runtime.txt; \
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

# ---------------------------------------------------------------------------------- runtime
FROM ${PYTHON_IMAGE} AS runtime

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

COPY --from=builder /opt/venv /opt/venv
# Defaults only: compose mounts the site's own files over these.
COPY machine.toml zenoh.json5 /etc/machine/
COPY zenoh/acl.json5 zenoh/tls.json5 /etc/machine/zenoh/

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
