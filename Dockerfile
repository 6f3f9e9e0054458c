# The image of every container `rse compose` writes (router, plant, monitor, agents):
# the package and its runtime dependencies on python:3.11-slim, run as the non-root
# user rse (uid 1000), the rse command as entry point. See docs/deployment.md.
#
#   docker build -t resilient-state-estimation .
#   docker build -t resilient-state-estimation --build-arg EXTRAS=lmi,plot .   # + rse report figures
#   docker run --rm resilient-state-estimation check /scenario/x.toml ...      # any rse command
FROM python:3.11-slim

# extras of the package to install: lmi (cvxpy) is what the H-infinity and inverter
# scenarios' offline designs need; add plot for the figures of rse report
ARG EXTRAS=lmi

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1

# only what the package is built from (no tests, docs, runs or credentials: .dockerignore)
COPY pyproject.toml README.md /tmp/src/
COPY agents /tmp/src/agents
COPY estimation /tmp/src/estimation
COPY transport /tmp/src/transport
COPY scenarios /tmp/src/scenarios

RUN pip install --no-cache-dir "/tmp/src[${EXTRAS}]" \
    && rm -rf /tmp/src \
    && useradd --create-home --uid 1000 --user-group --shell /usr/sbin/nologin rse \
    && mkdir -p /runs \
    && chown rse:rse /runs

USER rse
# the monitor's run directories go to /runs (rse compose mounts the volume "runs" there)
WORKDIR /home/rse

# Zenoh router, Rerun web viewer page, Rerun gRPC endpoint the page reads
EXPOSE 7447 9090 9876

# Healthy when the container's rse process is on the Zenoh network: the router listens
# on its --listen port, a client (plant, monitor, agent) has a connection to the router's
# port; any other command merely runs (python -m agents.healthcheck, exit 0 / 1 with one
# line of reason). The start period covers building the scenario before the session opens.
HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-m", "agents.healthcheck"]

ENTRYPOINT ["rse"]
CMD ["--help"]
