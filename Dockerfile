# voxfusion on a CUDA GPU server.
#   docker build -t voxfusion .
#   docker run --gpus all -p 8000:8000 -p 7447:7447 -v voxfusion-data:/data voxfusion
# The server runs as the unprivileged user `voxfusion` (uid 10001). A named volume (above) is writable as is;
# to use a host folder instead, make it writable for that uid (`sudo chown 10001 ./voxfusion-data`) or run as
# yourself: `docker run --user "$(id -u):$(id -g)" ... -v "$PWD/voxfusion-data:/data" voxfusion`.
FROM nvidia/cuda:12.4.1-cudnn-runtime-ubuntu22.04

# torch built for the base image's CUDA 12.4: 2.6.0 is the newest release on PyTorch's cu124 index (2.7 moved
# on to CUDA 11.8 / 12.6 / 12.8). Change the base image, TORCH_VERSION and TORCH_INDEX together.
ARG TORCH_VERSION=2.6.0
ARG TORCH_INDEX=https://download.pytorch.org/whl/cu124
ARG PIP_VERSION=26.3
ARG DEBIAN_FRONTEND=noninteractive
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1

# Ubuntu's packages are not pinned: the archive keeps only the current version of each, so a pin breaks the
# build at the next security update; the base image's tag fixes the release (22.04) they come from.
# gcc and libc6-dev build the engine's C kernels on first use (core/native/: a CPU session's interpolation,
# compositing and depth filter, ~1 s per kernel into ~/.cache/voxfusion/native); without them a session on the CPU
# (`--device cpu`, or a container started without a GPU) runs the slower PyTorch operators instead.
# hadolint ignore=DL3008
RUN apt-get update \
 && apt-get install -y --no-install-recommends python3.11 python3.11-venv \
        libusb-1.0-0 libgl1 libegl1 libglx0 libgomp1 libx11-6 gcc libc6-dev \
 && rm -rf /var/lib/apt/lists/* \
 && useradd --system --uid 10001 --user-group --create-home --home-dir /home/voxfusion voxfusion \
 && mkdir -p /data \
 && chown voxfusion:voxfusion /data

RUN python3.11 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH VIRTUAL_ENV=/opt/venv
WORKDIR /opt/voxfusion

# Dependencies before the source (this layer is rebuilt only when pyproject.toml changes): torch from the CUDA
# index, then the dependencies and the `baseline`, `server` and `cluster` extras as pyproject.toml lists them, with torch
# held at that build.
COPY pyproject.toml ./
RUN pip install "pip==${PIP_VERSION}" \
 && pip install "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX}" \
 && echo "torch==${TORCH_VERSION}" > /tmp/constraints.txt \
 && python -c 'import tomllib; p = tomllib.load(open("pyproject.toml", "rb"))["project"]; \
extras = p["optional-dependencies"]; print("\n".join(p["dependencies"] + extras["baseline"] + extras["server"] + extras["cluster"]))' \
        > /tmp/requirements.txt \
 && pip install --requirement /tmp/requirements.txt --constraint /tmp/constraints.txt \
 && rm /tmp/requirements.txt /tmp/constraints.txt

# The project itself (its dependencies are all in the layer above).
COPY README.md ./
COPY voxfusion ./voxfusion
COPY core ./core
COPY server ./server
COPY proto ./proto
COPY clients ./clients
COPY configs ./configs
RUN pip install --no-deps . \
 && rm -rf build ./*.egg-info

# Session database, recordings and checkpoints live in /data. zenoh listens on every interface of the container
# (port 7447, publish it with -p 7447:7447) with authentication and access control: credentials are generated
# once in /data/zenoh, and clients use /data/zenoh/client.json5 (`docker cp` it out). For another zenoh setup
# mount a config at /etc/voxfusion/zenoh.json5 and run `voxfusion serve ... --zenoh-config /etc/voxfusion/zenoh.json5`.
VOLUME ["/data"]
EXPOSE 8000 7447
USER 10001:10001
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s \
    CMD ["python3", "-c", "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"]
CMD ["voxfusion", "serve", "--host", "0.0.0.0", "--data-dir", "/data", "--zenoh-listen", "tcp/0.0.0.0:7447", \
     "--zenoh-secrets", "/data/zenoh"]
