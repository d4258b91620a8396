# One image for every Python service of deploy/docker-compose.yml (`python -m swarm deploy`):
# `python -m world`, `python -m agents.leader`, `python -m agents.follower --id K`.
# `docker compose up` at the repository root builds it; by hand: docker build -t koopman-swarm:local .
# The core install is all these processes need (docs/install.md); `swarm deploy`, which makes
# the TLS certificates, runs on the host with the [deploy] extra. A run.toml naming a DEM
# surface needs the [dem] extra in the world's image: pip install '.[dem]' below.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /src
COPY pyproject.toml README.md ./
COPY protocol/ protocol/
COPY world/ world/
COPY agents/ agents/
COPY swarm/ swarm/
RUN pip install . && rm -rf /src

# Non-root: the image's user swarm (uid 10001), or the uid the compose file gives (the owner of
# the deployment's secrets, deploy/.env). /results (the world's) and /state (a follower's
# checkpoint) are created here writable by either, so that a named volume mounted there
# starts so; each is mounted in one container only. numba caches compiled kernels in /tmp.
RUN useradd --create-home --uid 10001 swarm \
    && mkdir /results /state && chown swarm:swarm /results /state && chmod 1777 /results /state
USER swarm
WORKDIR /home/swarm
ENV NUMBA_CACHE_DIR=/tmp/numba-cache

CMD ["python", "-m", "swarm", "--help"]
