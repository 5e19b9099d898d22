# syntax=docker/dockerfile:1
# The machine daemon and the Rider in one image; compose.yaml runs it twice (docs/deploy.md).
#
#   docker build -t ride-machine:local .
#   docker run --rm ride-machine:local                  # the daemon on the simulator
#   docker run --rm ride-machine:local rider --help     # the Rider CLI / operator UI
#
# On a Revolution Pi the same image runs `machine run --hal revpi` with the process image
# device and the piCtory config passed in (docker/compose.revpi.yaml, docs/deploy.md).

ARG PYTHON_VERSION=3.11

# ---------------------------------------------------------------------------------- builder
# Wheels for the package and every dependency; a compiler for any dependency that has no
# wheel for the target platform (e.g. an armv7 Revolution Pi). Nothing of this stage but
# the wheels reaches the final image.
FROM python:${PYTHON_VERSION}-slim AS builder

# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /src
COPY pyproject.toml README.md ./
COPY schema/ schema/
COPY hal/ hal/
COPY service/ service/
COPY rider/ rider/
RUN pip wheel --no-cache-dir --wheel-dir /wheels ".[revpi,ui]"

# ---------------------------------------------------------------------------------- runtime
FROM python:${PYTHON_VERSION}-slim AS runtime

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# The wheels are bind-mounted from the builder, so they never become a layer of this image.
# --no-index installs exactly the versions the builder resolved (the pin DL3013 asks for).
# hadolint ignore=DL3013
RUN --mount=type=bind,from=builder,source=/wheels,target=/wheels \
    pip install --no-cache-dir --no-index --find-links=/wheels "ride-machine[revpi,ui]" \
    && groupadd --system --gid 10001 machine \
    && useradd --system --uid 10001 --gid 10001 --home-dir /var/lib/machine \
        --no-create-home --shell /usr/sbin/nologin machine \
    && mkdir -p /etc/machine /var/lib/machine \
    && chown 10001:10001 /var/lib/machine

# Defaults only: compose mounts the site's own machine.toml and zenoh.json5 over these.
COPY machine.toml zenoh.json5 /etc/machine/

USER 10001:10001
WORKDIR /var/lib/machine
# Calibration and persisted parameters live here; give it a named volume.
VOLUME ["/var/lib/machine"]

# Zenoh (the daemon listens, see zenoh.json5) and the operator UI (`rider ui`).
EXPOSE 7447/tcp 8080/tcp

# SIGTERM makes the daemon force every output safe first, then close its Zenoh session and
# exit 0; a SIGKILL (stop timeout exceeded) leaves no chance to do that in software.
STOPSIGNAL SIGTERM

# Healthy = the daemon answers a status query over Zenoh (exit 0); no answer exits 3. The
# machine is named so a second machine seen through a site router cannot make it ambiguous;
# m1 is the id in the machine.toml above (change both together).
HEALTHCHECK --interval=10s --timeout=5s --start-period=20s --retries=3 \
    CMD ["rider", "--connect", "tcp/127.0.0.1:7447", "--timeout", "2", "--machine", "m1", "status"]

CMD ["machine", "run", "--sim", "--config", "/etc/machine/machine.toml", "--zenoh-config", "/etc/machine/zenoh.json5", "--data-dir", "/var/lib/machine"]
