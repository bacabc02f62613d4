# posecast: the relay server and the bots share one image and one CLI.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
WORKDIR /app

COPY pyproject.toml README.md ./
COPY protocol ./protocol
COPY interp ./interp
COPY recorder ./recorder
COPY scenarios ./scenarios
COPY client ./client
COPY server ./server
RUN pip install . && useradd --create-home posecast

USER posecast
# Real traces can be mounted here (docker-compose.yml does); synthetic motion needs none.
ENV POSECAST_TRACES=/data/vr-traces
EXPOSE 8765
ENTRYPOINT ["posecast"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8765"]
