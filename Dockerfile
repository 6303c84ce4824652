# voxfusion on a CUDA GPU server.
#   docker build -t voxfusion .
#   docker run --gpus all -p 8000:8000 -v $PWD/voxfusion-data:/data voxfusion
FROM nvidia/cuda:12.4.1-cudnn-runtime-ubuntu22.04

ENV DEBIAN_FRONTEND=noninteractive PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
RUN apt-get update \
 && apt-get install -y --no-install-recommends python3.11 python3.11-venv python3-pip \
        libusb-1.0-0 libgl1 libegl1 libglx0 libgomp1 libx11-6 \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/voxfusion
RUN python3.11 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# The regular PyPI torch wheel ships its CUDA libraries.
RUN pip install --upgrade pip setuptools wheel && pip install torch

COPY pyproject.toml README.md ./
COPY voxfusion ./voxfusion
COPY core ./core
COPY server ./server
COPY proto ./proto
COPY clients ./clients
COPY configs ./configs
RUN pip install ".[baseline,server]"

# Session database, recordings and checkpoints live in /data. zenoh listens on every interface of the container
# (port 7447, publish it with -p 7447:7447); for another zenoh setup mount a config at
# /etc/voxfusion/zenoh.json5 and run `voxfusion serve ... --zenoh-config /etc/voxfusion/zenoh.json5`.
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s \
    CMD ["python3", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"]
CMD ["voxfusion", "serve", "--host", "0.0.0.0", "--data-dir", "/data", "--zenoh-listen", "tcp/0.0.0.0:7447"]
