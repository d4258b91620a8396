# One image for every Python service of deploy/docker-compose.yml (`python -m swarm deploy`):
# `python -m world`, `python -m agents.leader`, `python -m agents.follower --id K`.
# Build from the repository root: docker build -t koopman-swarm:local .
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

# Non-root. /results (the world's) and /state (a follower's checkpoint) are created here, owned
# by the user, so that a named volume mounted there starts with that ownership. numba caches
# compiled kernels under the user's home.
RUN useradd --create-home --uid 10001 swarm \
    && mkdir /results /state && chown swarm:swarm /results /state && chmod 0700 /state
USER swarm
WORKDIR /home/swarm
ENV NUMBA_CACHE_DIR=/home/swarm/.cache/numba

CMD ["python", "-m", "swarm", "--help"]
