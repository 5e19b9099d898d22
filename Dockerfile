# The machine daemon and the Rider in one image; compose.yaml runs it twice (docs/deploy.md).
#
#   docker build -t localhost/ride-machine:local .
#   podman build --format docker -t localhost/ride-machine:local .   # docker format keeps HEALTHCHECK
#   docker run --rm localhost/ride-machine:local                     # the daemon on the simulator
#   docker run --rm localhost/ride-machine:local rider --help        # the Rider CLI / operator UI
#
# No `# syntax=` line: the builder's own Dockerfile frontend reads everything here (RUN --mount
# included), and fetching another one from a registry fails on an offline site.
# Behind a private index or a TLS-intercepting proxy, pass pip's settings from outside
# (docs/deploy.md): --build-arg PIP_INDEX_URL=… or the build secrets `pip.conf` and `pip-ca`.

# Fully qualified, so podman resolves it without a registries.conf alias.
ARG PYTHON_IMAGE=docker.io/library/python:3.11-slim

# ---------------------------------------------------------------------------------- builder
# Every dependency at its locked version (hashes checked) and the package itself, installed in
# the virtualenv /opt/venv: the one thing the runtime stage takes from here.
FROM ${PYTHON_IMAGE} AS builder

ARG PIP_INDEX_URL
ARG PIP_EXTRA_INDEX_URL
ARG PIP_TRUSTED_HOST
# armv7 (32-bit RevPi OS) has no wheels for some dependencies: 1 installs a compiler for them.
ARG WITH_COMPILER=0
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_ROOT_USER_ACTION=ignore

WORKDIR /src
COPY requirements/runtime.txt requirements/build.txt requirements/

# The secrets are mounted for this one step and never become a layer; absent ones are skipped.
# hadolint ignore=DL3008
RUN --mount=type=secret,id=pip.conf,target=/etc/pip.conf \
    --mount=type=secret,id=pip-ca,target=/run/secrets/pip-ca \
    set -eu; \
    if [ "$WITH_COMPILER" = 1 ]; then \
        apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev libffi-dev \
        && rm -rf /var/lib/apt/lists/*; \
    fi; \
    if [ -s /run/secrets/pip-ca ]; then export PIP_CERT=/run/secrets/pip-ca; fi; \
    python -m venv --without-pip /opt/venv; \
    pip --python /opt/venv/bin/python install --require-hashes --no-deps -r requirements/runtime.txt; \
    pip install --require-hashes --no-deps -r requirements/build.txt

COPY pyproject.toml README.md ./
COPY schema/ schema/
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
    PATH=/opt/venv/bin:$PATH

RUN groupadd --system --gid 10001 machine \
    && useradd --system --uid 10001 --gid 10001 --home-dir /var/lib/machine \
        --no-create-home --shell /usr/sbin/nologin machine \
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

# Healthy = the daemon answers a status query over Zenoh (exit 0); no answer exits 3. m1 is the
# id in the machine.toml above (change both together). The first check comes one interval after
# the start (compose adds a 1 s start interval where the engine has one; podman 4 has not).
HEALTHCHECK --interval=5s --timeout=5s --start-period=30s --retries=3 \
    CMD ["rider", "--connect", "tcp/127.0.0.1:7447", "--timeout", "2", "--machine", "m1", "status"]

CMD ["machine", "run", "--sim", "--config", "/etc/machine/machine.toml", "--zenoh-config", "/etc/machine/zenoh.json5", "--data-dir", "/var/lib/machine"]
