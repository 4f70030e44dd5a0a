# GPU image for build + serve: `fmgs-server` on a mounted scene repository, health-checked over gRPC.
#   docker build -t fmgs .
#   docker run --gpus all -p 50051:50051 -v "$PWD/models:/models" fmgs
# The same image runs the Ray Serve deployment (fmgs[ray]: ray[serve] comes with the pinned environment):
# `fmgs-server --ray ADDRESS`, or as the head and worker image of a KubeRay RayService
# (deploy/kuberay/rayservice.yaml; KubeRay replaces the entrypoint with its `ray start` command).
# Stage 1 compiles (CUDA toolkit, compilers); stage 2 carries only the virtual environment and the runtime.

ARG CUDA_VERSION=12.8.1
ARG TORCH_INDEX=https://download.pytorch.org/whl/cu128

FROM nvidia/cuda:${CUDA_VERSION}-cudnn-devel-ubuntu22.04 AS build
ARG TORCH_INDEX
ENV DEBIAN_FRONTEND=noninteractive PIP_NO_CACHE_DIR=1 \
    TORCH_CUDA_ARCH_LIST="8.0;8.6;8.9;9.0" MAX_JOBS=8
RUN apt-get update && apt-get install -y --no-install-recommends \
        python3.11 python3.11-venv python3.11-dev build-essential git \
    && rm -rf /var/lib/apt/lists/*
RUN python3.11 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
COPY requirements/ requirements/
# CUDA torch first (same version as the CPU pin), then the pinned environment (ray[serve] included: the
# fmgs[ray] extra's pin), then gsplat compiled ahead of time for the listed GPU architectures (no
# compiler is needed at run time).
RUN pip install --upgrade pip \
    && pip install torch==2.13.0 --index-url ${TORCH_INDEX} \
    && pip install -r requirements/cpu.txt \
    && pip install --no-deps -r requirements/nodeps.txt \
    && pip install --no-build-isolation "gsplat>=1.5,<1.6"
COPY pyproject.toml README.md ./
COPY fmgs/ fmgs/
COPY fmgs_server/ fmgs_server/
COPY fmgs_client/ fmgs_client/
COPY fmgs_wire/ fmgs_wire/
COPY proto/ proto/
COPY scripts/ scripts/
RUN python scripts/gen_proto.py --check && pip install --no-deps .

FROM nvidia/cuda:${CUDA_VERSION}-cudnn-runtime-ubuntu22.04
ENV DEBIAN_FRONTEND=noninteractive PATH=/opt/venv/bin:$PATH PYTHONUNBUFFERED=1
COPY requirements/apt.txt /tmp/apt.txt
# wget: KubeRay's default liveness/readiness probes of Ray pods run `wget` in the container.
RUN apt-get update && apt-get install -y --no-install-recommends python3.11 wget \
        $(grep -v '^#' /tmp/apt.txt) \
    && rm -rf /var/lib/apt/lists/* /tmp/apt.txt \
    && useradd --create-home --uid 10001 fmgs
COPY --from=build /opt/venv /opt/venv
COPY models/ /models/
USER fmgs
EXPOSE 50051
VOLUME ["/models"]
HEALTHCHECK --interval=30s --timeout=5s --start-period=120s --retries=3 \
    CMD ["fmgs-client", "--address", "127.0.0.1:50051", "--timeout", "4", "health"]
ENTRYPOINT ["fmgs-server", "--models", "/models", "--host", "0.0.0.0", "--port", "50051", "--device", "cuda"]
