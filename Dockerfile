# posecast: the relay server and the bots share one image and one CLI.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
WORKDIR /app

# pyproject.toml names README.md (readme) and LICENSE (license-files): the build needs both.
COPY pyproject.toml README.md LICENSE ./
COPY protocol ./protocol
COPY interp ./interp
COPY recorder ./recorder
# scenarios/ carries its data: tiers, the synthetic suite and scenarios/data/traces,
# the bundled real traces behind `traces:sample`, `traces:dev` and `traces:eval`
# (package data).
COPY scenarios ./scenarios
COPY client ./client
COPY server ./server
# posecast/: the CLI and what composes server, client and experiments.
COPY posecast ./posecast
COPY setup.py ./
# The check runs from / so that it imports the installed package, not /app: the
# image is not built if the wheel left the bundled traces out. gcc is there for the
# build only: it compiles the codec's C accelerator (protocol/_speedups.c; without
# it the relay runs the pure-Python codec, at several times the CPU per pose) and
# is removed in the same layer.
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev \
    && pip install . \
    && apt-get purge -y --auto-remove gcc libc6-dev && rm -rf /var/lib/apt/lists/* \
    && cd / && python -c "from posecast.scenarios.traces import find_traces; print(len(find_traces('traces:sample')), 'sample traces')" \
    && python -c "from posecast.protocol import codec; print('codec:', codec.IMPLEMENTATION)" \
    && useradd --create-home posecast

USER posecast
# Another copy of the full trace sets (traces:dev, traces:eval) is read from here
# when mounted (docker-compose.yml does, optionally); a split it lacks is read from
# the sets bundled in the package.
ENV POSECAST_TRACES=/data/vr-traces
EXPOSE 8765
ENTRYPOINT ["posecast"]
# The secret comes from the environment (POSECAST_SECRET), never from the image.
CMD ["serve", "--host", "0.0.0.0", "--port", "8765"]
