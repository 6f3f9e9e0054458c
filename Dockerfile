# The images of the containers `rse compose` writes, one build target per role, all on
# python:3.11-slim, run as the non-root user rse (uid 1000). See docs/deployment.md.
#
#   target   tag (what rse compose names)            what it carries
#   agent    resilient-state-estimation-agent        the package + numpy, eclipse-zenoh, msgpack, click, rich,
#                                                    psutil: rse router, rse agent --team (an agent's slice),
#                                                    rse plant --team (the plant's slice)
#   monitor  resilient-state-estimation-monitor      the agent image + rerun-sdk, pyarrow, pydantic:
#                                                    rse monitor --team (the built experiment)
#   full     resilient-state-estimation (default)    the package with all its dependencies and the lmi
#                                                    extra (cvxpy): the offline designs, every rse command
#
#   docker build -t resilient-state-estimation .                                  # full
#   docker build --target agent -t resilient-state-estimation-agent .
#   docker build --target monitor -t resilient-state-estimation-monitor .
#   docker build -t resilient-state-estimation --build-arg EXTRAS=lmi,plot .      # + rse report figures
#   docker run --rm resilient-state-estimation check /scenario/x.toml ...         # any rse command
#
# Every role image runs as rse in /home/rse (the monitor's run directories go to /runs, where
# rse compose mounts the volume "runs") with the same health check: healthy when the
# container's rse process is on the Zenoh network (the router listens on its --listen port,
# a client - plant, monitor, agent - has a connection to the router's port; any other
# command merely runs: python -m agents.healthcheck, exit 0 / 1 with one line of reason).
# The start period covers building the scenario before the session opens; the timeout is
# generous for loaded hosts. (They are set in the role stages, not in base, so that a
# change to them does not rebuild the dependency layers.)
#
# pip reaches its index as pip does: PIP_INDEX_URL, PIP_EXTRA_INDEX_URL, PIP_TRUSTED_HOST
# and the proxy variables can be given with --build-arg (they are not kept in the images).
# The role stages list their requirements; each must be one of pyproject.toml's
# (tests/deploy/test_compose.py checks it).

FROM python:3.11-slim AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1
RUN useradd --create-home --uid 1000 --user-group --shell /usr/sbin/nologin rse \
    && mkdir -p /runs \
    && chown rse:rse /runs

# the package itself as a wheel, without its dependencies (what the role images add last),
# and the requirements of the full image from pyproject.toml (a layer of its own that only
# a change of the requirements rebuilds). Only what the package is built from: no tests,
# docs, runs or credentials (.dockerignore)
FROM base AS wheel
COPY pyproject.toml README.md /tmp/src/
COPY agents /tmp/src/agents
COPY estimation /tmp/src/estimation
COPY transport /tmp/src/transport
COPY scenarios /tmp/src/scenarios
COPY rse /tmp/src/rse
# extras of the full image: lmi (cvxpy) is what the H-infinity and inverter scenarios'
# offline designs need, cluster (Dask) what rse compose --dask-workers runs; add plot for the figures of rse report
ARG EXTRAS=lmi,cluster
ARG PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_TRUSTED_HOST
RUN pip wheel --no-deps --wheel-dir /wheels /tmp/src \
    && python -c "import sys, tomllib; p = tomllib.load(open('/tmp/src/pyproject.toml', 'rb'))['project']; \
print(*p['dependencies'], *(r for e in sys.argv[1].split(',') if e for r in p['optional-dependencies'][e]), sep='\n')" \
       "${EXTRAS}" > /wheels/requirements-full.txt

# what an agent process imports: numpy, Zenoh, msgpack (click and rich for the rse command
# and its messages, psutil for the health check)
FROM base AS agent-deps
ARG PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_TRUSTED_HOST
RUN pip install "numpy>=1.26" "eclipse-zenoh>=1.0" "uvloop>=0.19; sys_platform != 'win32'" "msgpack>=1.0" "click>=8.1" "rich>=13" "psutil>=5.9"

# the monitor's on top: the Rerun recording and stream, the metrics table, and pydantic (the
# built experiment it reads holds the validated scenario: its bounds, its names). rerun_cli
# is the native viewer (rr.spawn, 280 MB), which a container never starts: the web viewer
# it serves and the recording file are rerun_bindings'
FROM agent-deps AS monitor-deps
ARG PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_TRUSTED_HOST
RUN pip install "rerun-sdk>=0.20" "pyarrow>=14" "pydantic>=2.5" \
    && python -c "import rerun_cli, shutil, os; shutil.rmtree(os.path.dirname(rerun_cli.__file__))"

# (the package comes last in each role image: a code change rebuilds only that layer)
FROM agent-deps AS agent
COPY --from=wheel /wheels/*.whl /wheels/
RUN pip install --no-deps /wheels/*.whl && rm -rf /wheels
USER rse
WORKDIR /home/rse
HEALTHCHECK --interval=10s --timeout=10s --start-period=60s --retries=3 \
    CMD ["python", "-m", "agents.healthcheck"]
EXPOSE 7447
ENTRYPOINT ["rse"]
CMD ["--help"]

FROM monitor-deps AS monitor
COPY --from=wheel /wheels/*.whl /wheels/
RUN pip install --no-deps /wheels/*.whl && rm -rf /wheels
USER rse
WORKDIR /home/rse
HEALTHCHECK --interval=10s --timeout=10s --start-period=60s --retries=3 \
    CMD ["python", "-m", "agents.healthcheck"]
# Zenoh, Rerun web viewer page, Rerun gRPC endpoint the page reads
EXPOSE 7447 9090 9876
ENTRYPOINT ["rse"]
CMD ["--help"]

# every rse command, the offline designs included (the router, the plant, one-shot designs)
FROM base AS full
ARG PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_TRUSTED_HOST
COPY --from=wheel /wheels/requirements-full.txt /tmp/
RUN pip install -r /tmp/requirements-full.txt && rm /tmp/requirements-full.txt
COPY --from=wheel /wheels/*.whl /wheels/
RUN pip install --no-deps /wheels/*.whl && rm -rf /wheels
USER rse
WORKDIR /home/rse
HEALTHCHECK --interval=10s --timeout=10s --start-period=60s --retries=3 \
    CMD ["python", "-m", "agents.healthcheck"]
# Zenoh router, Rerun web viewer page, Rerun gRPC endpoint the page reads
EXPOSE 7447 9090 9876
ENTRYPOINT ["rse"]
CMD ["--help"]
