# Image for build + serve: `fmgs-server` on a mounted scene repository, health-checked over gRPC.
# Two flavours from one file (scripts/image.sh builds either with buildah, without a daemon):
#   cuda (default): docker build -t fmgs:0.1.0-cuda .
#                   docker run --gpus all -p 50051:50051 -v "$PWD/models:/models" fmgs:0.1.0-cuda
#   cpu:            docker build -t fmgs:0.1.0-cpu --build-arg FLAVOUR=cpu \
#                     --build-arg BUILD_BASE=debian:bookworm-slim --build-arg RUNTIME_BASE=debian:bookworm-slim \
#                     --build-arg TORCH_INDEX=https://download.pytorch.org/whl/cpu .
# The same image runs the Ray Serve deployment (fmgs[ray]: ray[serve] comes with the pinned environment):
# `fmgs-server --ray ADDRESS`, or as the head and worker image of a KubeRay RayService
# (deploy/kuberay/rayservice.yaml; KubeRay replaces the entrypoint with its `ray start` command).
# Stage 1 compiles (compilers; the CUDA toolkit in the cuda flavour); stage 2 carries only the virtual
# environment and the runtime libraries. Both bases must offer python3.11 from apt (Ubuntu 22.04, Debian 12).

ARG BUILD_BASE=nvidia/cuda:12.8.1-cudnn-devel-ubuntu22.04
ARG RUNTIME_BASE=nvidia/cuda:12.8.1-cudnn-runtime-ubuntu22.04

FROM ${BUILD_BASE} AS build
# cuda: gsplat compiled ahead of time; cpu: no gsplat (the CPU rasteriser serves).
ARG FLAVOUR=cuda
# Where torch comes from: the PyTorch index of the flavour (cu128 or cpu), or, when TORCH_WHEELS names a
# folder mounted into the build, a local wheel of the same version from it (its dependencies from PyPI).
ARG TORCH_INDEX=https://download.pytorch.org/whl/cu128
ARG TORCH_WHEELS=
# A CA bundle for pip, mounted into the build, where HTTPS to the package index passes a proxy that signs
# with its own CA (empty: pip's own bundle).
ARG PIP_CERT_FILE=
ENV DEBIAN_FRONTEND=noninteractive PIP_NO_CACHE_DIR=1 \
    TORCH_CUDA_ARCH_LIST="8.0;8.6;8.9;9.0" MAX_JOBS=8
RUN apt-get update && apt-get install -y --no-install-recommends \
        python3.11 python3.11-venv python3.11-dev build-essential git ca-certificates \
    && rm -rf /var/lib/apt/lists/*
RUN python3.11 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
WORKDIR /src
COPY requirements/ requirements/
# torch of the flavour first (same version as the CPU pin), then the pinned environment (ray[serve]
# included: the fmgs[ray] extra's pin), then, for cuda, gsplat built from its source for the listed GPU
# architectures. PyPI's gsplat wheel has no compiled kernels (it compiles them with nvcc on first use, and
# the runtime stage has no nvcc), so the build fails unless the compiled module gsplat.csrc imports.
RUN case "$FLAVOUR" in cuda|cpu) ;; *) echo "FLAVOUR must be cuda or cpu, not '$FLAVOUR'" >&2; exit 2;; esac \
    && if [ -n "$PIP_CERT_FILE" ]; then export PIP_CERT="$PIP_CERT_FILE"; fi \
    && pip install --upgrade pip \
    && if [ -n "$TORCH_WHEELS" ]; then pip install --find-links "$TORCH_WHEELS" torch==2.13.0; \
       else pip install torch==2.13.0 --index-url "$TORCH_INDEX"; fi \
    && pip install -r requirements/cpu.txt \
    && pip install --no-deps -r requirements/nodeps.txt \
    && if [ "$FLAVOUR" = cuda ]; then \
         pip install --no-build-isolation "gsplat @ git+https://github.com/nerfstudio-project/gsplat.git@v1.5.3" \
         && python -c "import gsplat.csrc"; fi
COPY pyproject.toml README.md ./
COPY fmgs/ fmgs/
COPY fmgs_server/ fmgs_server/
COPY fmgs_client/ fmgs_client/
COPY fmgs_wire/ fmgs_wire/
COPY proto/ proto/
COPY scripts/ scripts/
RUN python scripts/gen_proto.py --check \
    && if [ -n "$PIP_CERT_FILE" ]; then export PIP_CERT="$PIP_CERT_FILE"; fi \
    && pip install --no-deps . \
    && mkdir -p /etc/fmgs && printf 'device = "%s"\n' "$FLAVOUR" > /etc/fmgs/image.toml

FROM ${RUNTIME_BASE}
ENV DEBIAN_FRONTEND=noninteractive PATH=/opt/venv/bin:$PATH PYTHONUNBUFFERED=1
COPY requirements/apt.txt /tmp/apt.txt
# wget: KubeRay's default liveness/readiness probes of Ray pods run `wget` in the container.
# NUMBA_CACHE_DIR: numba's compiled kernels, written by the fmgs user (site-packages is root's).
ENV NUMBA_CACHE_DIR=/var/cache/fmgs/numba
RUN apt-get update && apt-get install -y --no-install-recommends python3.11 wget \
        $(grep -v '^#' /tmp/apt.txt) \
    && rm -rf /var/lib/apt/lists/* /tmp/apt.txt \
    && useradd --create-home --uid 10001 fmgs \
    && mkdir -p "$NUMBA_CACHE_DIR" && chown fmgs "$NUMBA_CACHE_DIR"
COPY --from=build /opt/venv /opt/venv
# The flavour's settings (device = "cuda" or "cpu"); flags given to `docker run` override them.
COPY --from=build /etc/fmgs/image.toml /etc/fmgs/image.toml
COPY models/ /models/
USER fmgs
# The kernels compiled once, here, into NUMBA_CACHE_DIR: a start on a CPU of the build machine's model
# compiles nothing; on another model numba compiles once more into the same folder (mount a volume there
# to keep that across containers). On the CPU whatever the flavour: the kernels are CPU code.
RUN fmgs-server --models /models --device cpu --backend cpu --precompile
EXPOSE 50051
VOLUME ["/models"]
HEALTHCHECK --interval=30s --timeout=5s --start-period=120s --retries=3 \
    CMD ["fmgs-client", "--address", "127.0.0.1:50051", "--timeout", "4", "health"]
# --preload: health says NOT_SERVING until every scene, its text encoder and its kernels are warm. No
# admin token file: LoadScene/UnloadScene/ReloadScene are refused (mount one and pass --admin-token-file).
ENTRYPOINT ["fmgs-server", "--config", "/etc/fmgs/image.toml", "--models", "/models", "--host", "0.0.0.0", "--port", "50051", "--preload"]
