#!/usr/bin/env bash
# Build the FMGS image without a daemon (buildah), run it (podman), and check it from outside with the
# thin client: health SERVING, list, a text query and a render of the bundled demo scene (each timed from
# SERVING), an unauthenticated UnloadScene refused, the server running as the image's non-root user, and
# the image's own HEALTHCHECK command. Writes a report only when asked (--report FILE, e.g.
# benchmarks/results/IMAGE.md); removes the untagged build-stage image it made unless --keep-build-stage.
#
#   bash scripts/image.sh [--flavour cpu|cuda] [--base IMAGE] [--tag NAME] [--no-run] [--report FILE]
#                         [--keep-build-stage]
#
# --flavour cpu (default): Debian 12 bases, CPU torch, no gsplat. The base is pulled from a registry
#   when one answers, else made with debootstrap from the Debian mirror (FMGS_DEBIAN_MIRROR) and kept in
#   container storage as localhost/fmgs-debian:bookworm. torch comes from the local wheel folder named by
#   FMGS_TORCH_WHEELS (default: pip's find-links, when it holds a torch wheel), mounted into the build,
#   else from the PyTorch CPU index.
# --flavour cuda: the Dockerfile's CUDA bases (need a registry) and the CUDA torch index.
# --base IMAGE: the base of both stages instead (e.g. the CUDA flavour's steps on the Debian base, as far
#   as they go without the CUDA toolkit). FMGS_TORCH_INDEX replaces the flavour's torch index.
# The tag defaults to fmgs:VERSION-FLAVOUR (pyproject's version); deploy/kuberay/rayservice.yaml names
# the cuda one. Needs root (or a working rootless buildah/podman); installs buildah, podman, runc and
# debootstrap with apt when missing. Container storage: FMGS_STORAGE_DRIVER (default overlay where it
# works, else vfs), chroot isolation (no user namespaces needed). The check publishes the container's
# port 50051 on 127.0.0.1:FMGS_IMAGE_PORT (default 50051).
set -euo pipefail
cd "$(dirname "$0")/.."
t_start=$(date +%s)

flavour=cpu
tag=""
run=1
report=""
keep_build_stage=0
while [ $# -gt 0 ]; do
  case "$1" in
    --flavour) flavour=$2; shift 2 ;;
    --tag) tag=$2; shift 2 ;;
    --base) FMGS_IMAGE_BASE=$2; shift 2 ;;
    --no-run) run=0; shift ;;
    --report) report=$2; shift 2 ;;
    --keep-build-stage) keep_build_stage=1; shift ;;
    -h|--help) sed -n '2,25p' "$0"; exit 0 ;;
    *) echo "image.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
case "$flavour" in cpu|cuda) ;; *) echo "image.sh: --flavour must be cpu or cuda, not '$flavour'" >&2; exit 2 ;; esac
version=$(sed -n 's/^version = "\(.*\)"/\1/p' pyproject.toml | head -1)
tag=${tag:-fmgs:$version-$flavour}
port=${FMGS_IMAGE_PORT:-50051}
export BUILDAH_ISOLATION=chroot
# One container store for both tools: overlay where the kernel allows it, else vfs (works anywhere).
driver=${FMGS_STORAGE_DRIVER:-overlay}
bah() { buildah --storage-driver "$driver" "$@"; }
# runc: crun refuses hosts with hybrid cgroups (v1 controllers beside v2), runc runs there and anywhere.
pod() { podman --storage-driver "$driver" --runtime runc "$@"; }
say() { printf '[image.sh] %s\n' "$*" >&2; }

need=()
for tool in buildah podman runc debootstrap; do command -v "$tool" >/dev/null || need+=("$tool"); done
if [ ${#need[@]} -gt 0 ]; then
  [ "$(id -u)" -eq 0 ] || { echo "image.sh: install ${need[*]} (Debian packages) or run as root" >&2; exit 1; }
  say "installing ${need[*]}"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

if [ -z "${FMGS_STORAGE_DRIVER:-}" ] && ! buildah --storage-driver overlay images >/dev/null 2>&1; then
  driver=vfs
fi

# ---------------------------------------------------------------- bases
debian_base() {
  # A Debian 12 base: from a registry if one answers within a minute, else debootstrapped here.
  local pulled=docker.io/library/debian:bookworm-slim local=localhost/fmgs-debian:bookworm
  if [ -n "${FMGS_IMAGE_BASE:-}" ]; then echo "$FMGS_IMAGE_BASE"; return; fi
  if bah inspect --type image "$local" >/dev/null 2>&1; then echo "$local"; return; fi
  if timeout 60 bah pull -q "$pulled" >/dev/null 2>&1; then echo "$pulled"; return; fi
  local mirror=${FMGS_DEBIAN_MIRROR:-http://deb.debian.org/debian}
  local root
  root=$(mktemp -d /var/tmp/fmgs-rootfs.XXXXXX)
  say "no registry answered: debootstrap bookworm from $mirror"
  debootstrap --variant=minbase bookworm "$root" "$mirror" >&2
  rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
  local ctr mnt
  ctr=$(bah from scratch)
  mnt=$(bah mount "$ctr")
  cp -a "$root"/. "$mnt"/
  bah umount "$ctr" >/dev/null
  bah config --env PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin --cmd /bin/bash "$ctr"
  bah commit -q "$ctr" "$local" >/dev/null
  bah rm "$ctr" >/dev/null
  rm -rf "$root"
  echo "$local"
}

t_base=$(date +%s)
args=(--build-arg "FLAVOUR=$flavour")
vols=()
if [ "$flavour" = cpu ]; then
  base=$(debian_base)
  args+=(--build-arg "BUILD_BASE=$base" --build-arg "RUNTIME_BASE=$base")
  wheels=${FMGS_TORCH_WHEELS:-$(pip config get global.find-links 2>/dev/null || true)}
  if [ -n "$wheels" ] && ls "$wheels"/torch-*cpu*.whl >/dev/null 2>&1; then
    say "torch from the local wheel folder $wheels"
    vols+=(-v "$(cd "$wheels" && pwd):/wheels:ro")
    args+=(--build-arg TORCH_WHEELS=/wheels)
  else
    args+=(--build-arg "TORCH_INDEX=${FMGS_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}")
  fi
elif [ -n "${FMGS_IMAGE_BASE:-}" ]; then
  base=$FMGS_IMAGE_BASE
  args+=(--build-arg "BUILD_BASE=$base" --build-arg "RUNTIME_BASE=$base")
else
  base="the Dockerfile's CUDA bases"
fi
if [ "$flavour" = cuda ] && [ -n "${FMGS_TORCH_INDEX:-}" ]; then
  args+=(--build-arg "TORCH_INDEX=$FMGS_TORCH_INDEX")
fi
# pip inside the build trusts the CA bundle pip trusts here (a proxy that signs with its own CA).
cert=${PIP_CERT:-$(pip config get global.cert 2>/dev/null || true)}
if [ -n "$cert" ] && [ -f "$cert" ]; then
  vols+=(-v "$(readlink -f "$cert"):/run/fmgs-pip-ca.crt:ro")
  args+=(--build-arg PIP_CERT_FILE=/run/fmgs-pip-ca.crt)
fi

# ---------------------------------------------------------------- build
base_s=$(( $(date +%s) - t_base ))
say "building $tag ($flavour, base: $base)"
t0=$(date +%s)
dangling_before=$(bah images --filter dangling=true --quiet --no-trunc | sort)
bah bud --format docker --layers "${vols[@]}" "${args[@]}" -t "$tag" -f Dockerfile . >&2
build_s=$(( $(date +%s) - t0 ))
# The build stage is left behind untagged (several GB): remove the untagged images this build made.
if [ "$keep_build_stage" = 0 ]; then
  made=$(comm -13 <(echo "$dangling_before") <(bah images --filter dangling=true --quiet --no-trunc | sort))
  for id in $made; do bah rmi "$id" >/dev/null 2>&1 || say "could not remove the untagged image $id"; done
fi
size=$(pod image inspect --format '{{.Size}}' "$tag")
say "built $tag in ${build_s}s, $(( size / 1024 / 1024 )) MiB"

# The runtime stage carries no compilers, and runs as the non-root user.
# One working container for the looks inside: no compilers, and where the size goes (largest packages).
ctr=$(bah from "$tag")
compilers=$(bah run "$ctr" -- sh -c \
  'for c in cc gcc g++ c++ clang nvcc make; do command -v "$c" || true; done' 2>/dev/null || true)
largest=$(bah run "$ctr" -- sh -c 'du -sm /opt/venv/lib/python3.11/site-packages/* | sort -rn | head -6' \
  | awk '{sub(".*/", "", $2); printf "%s%s %s MiB", sep, $2, $1; sep=", "}')
bah rm "$ctr" >/dev/null
[ -z "$compilers" ] || { echo "image.sh: the runtime stage carries compilers: $compilers" >&2; exit 1; }
user=$(bah inspect --type image --format '{{.Docker.Config.User}}' "$tag")
[ "$user" = fmgs ] || { echo "image.sh: the image runs as '$user', not fmgs" >&2; exit 1; }

checks="not run (--no-run)"
if [ "$run" = 1 ]; then
  # ------------------------------------------------------------ run and check from outside
  # The thin client: a venv with grpcio, its health stubs, protobuf, numpy and this package, no torch.
  cvenv=${FMGS_CLIENT_VENV:-$HOME/.cache/fmgs/client-venv}
  if [ ! -x "$cvenv/bin/fmgs-client" ]; then
    python3 -m venv "$cvenv"
    "$cvenv/bin/pip" install -q numpy==2.4.6 grpcio==1.85.1 grpcio-health-checking==1.85.1 protobuf==7.36.2
  fi
  "$cvenv/bin/pip" install -q --no-deps --force-reinstall . >/dev/null
  if "$cvenv/bin/python" -c "import torch" 2>/dev/null; then echo "image.sh: torch found in the client venv" >&2; exit 1; fi
  name=fmgs-image-check-$$
  out=$(mktemp -d)
  pod rm -f "$name" >/dev/null 2>&1 || true
  # Own network namespace, the gRPC port published on loopback only. Explicit ulimits: podman's defaults
  # for root raise them past what some hosts allow ("error setting rlimit type 7" without them). No health timer (it needs systemd): the image's
  # HEALTHCHECK runs below with `podman healthcheck run`, as the timer would run it.
  # (podman still logs that it found no systemd for health timers: kept in $out/podman.log.)
  t_run=$(date +%s%N)
  pod run -d --name "$name" -p "127.0.0.1:$port:50051" --ulimit nofile=4096:4096 --ulimit nproc=4096:4096 \
    --health-interval disable "$tag" >/dev/null 2>"$out/podman.log" || { cat "$out/podman.log" >&2; exit 1; }
  trap 'pod logs "$name" > "$out/server.log" 2>&1 || true; pod rm -f "$name" >/dev/null 2>&1 || true' EXIT
  client() { "$cvenv/bin/fmgs-client" --address "127.0.0.1:$port" --timeout 60 "$@"; }
  ms() { echo $(( ($(date +%s%N) - $1) / 1000000 )); }
  # From the container's start to health SERVING (polled every 0.2 s), then the first text query and the
  # first render after SERVING, each from a fresh client process, timed from outside (--preload: the
  # server says SERVING only once the scene, its text encoder and its kernels are ready).
  first_answers() {  # $1: label ("cold", "restart"), $2: start time in ns
    local t
    for _ in $(seq 1 1200); do
      if [ "$(client health 2>/dev/null)" = SERVING ]; then break; fi
      if [ "$(pod inspect --format '{{.State.Running}}' "$name")" != true ]; then
        pod logs "$name" >&2; echo "image.sh: the container exited" >&2; exit 1
      fi
      sleep 0.2
    done
    ready_ms=$(ms "$2")
    [ "$(client health)" = SERVING ] || { echo "image.sh: health never answered SERVING" >&2; exit 1; }
    t=$(date +%s%N)
    client query demo "red cube" "blue ball" --top-k 50 --instances --rows 3 | tee "$out/query.txt" >&2
    query_ms=$(ms "$t")
    t=$(date +%s%N)
    client render demo "red cube" --out "$out/relevancy.png" --rgb "$out/rgb.png" >&2
    render_ms=$(ms "$t")
    say "$1: SERVING ${ready_ms} ms after start, then first text query ${query_ms} ms, first render ${render_ms} ms"
    timings="$timings$1: SERVING after ${ready_ms} ms, first text query ${query_ms} ms, first render ${render_ms} ms; "
  }
  timings=""
  first_answers cold "$t_run"
  client list | tee "$out/list.txt" >&2
  grep -q demo "$out/list.txt" || { echo "image.sh: list lacks the demo scene" >&2; exit 1; }
  # The same container stopped and started again (its writable layer kept): a restart.
  pod stop -t 20 "$name" >/dev/null
  t_run=$(date +%s%N)
  pod start "$name" >/dev/null
  first_answers restart "$t_run"
  # Admin calls are closed in the image (no admin token file): an unauthenticated UnloadScene is refused.
  "$cvenv/bin/python" - "127.0.0.1:$port" <<'PY' >&2 || { echo "image.sh: UnloadScene was not refused" >&2; exit 1; }
import sys
from fmgs_client import FmgsClient, FmgsError
with FmgsClient(sys.argv[1], timeout=30) as c:
    try:
        c.unload("demo")
    except FmgsError as e:
        assert e.code == "PERMISSION_DENIED", e
        print(f"UnloadScene refused: {e}")
    else:
        sys.exit("UnloadScene answered without a token")
    assert [s.state for s in c.list_scenes() if s.name == "demo"] == ["ready"], "demo not loaded"
PY
  python3 - "$out/relevancy.png" <<'PY'
import struct, sys
data = open(sys.argv[1], "rb").read()
assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
w, h = struct.unpack(">II", data[16:24])
assert w > 0 and h > 0, (w, h)
print(f"relevancy PNG {w}x{h}", file=sys.stderr)
PY
  uid=$(pod exec "$name" id -u)
  [ "$uid" = 10001 ] || { echo "image.sh: the server runs as uid $uid" >&2; exit 1; }
  proc_user=$(pod top "$name" user comm | awk 'NR > 1 && $2 ~ /fmgs-server|python/ {print $1; exit}')
  # The image's own health check (HEALTHCHECK CMD, run inside the container).
  pod healthcheck run "$name" >&2 2>>"$out/podman.log" \
    || { cat "$out/podman.log" >&2; echo "image.sh: the image's health check failed" >&2; exit 1; }
  checks="${timings}each answer from a fresh client process; list, unauthenticated UnloadScene refused, uid $uid (process user ${proc_user:-?}), HEALTHCHECK passed"
  say "checks: $checks"
fi

if [ -z "$report" ]; then
  say "no report written (--report FILE writes one)"
  exit 0
fi
mkdir -p "$(dirname "$report")"
cat >"$report" <<EOF
# The container image

Made by \`bash scripts/image.sh --flavour $flavour\` on $(date -u +%Y-%m-%d) at commit
$(git rev-parse --short HEAD 2>/dev/null || echo unknown) ($(nproc) cores, $(uname -m);
buildah $(buildah --version | awk '{print $3}'), $driver storage, chroot isolation).

| what | value |
|---|---|
| tag | \`$tag\` |
| flavour | $flavour |
| base | \`$base\` |
| base image made (debootstrap) or found, this run | $base_s s |
| build time (\`buildah bud\`, wall, this run) | $build_s s |
| whole command (base, build, checks), this run | $(( $(date +%s) - t_start )) s |
| image size | $(( size / 1024 / 1024 )) MiB |
| largest Python packages in it | $largest |
| compilers in the runtime stage | none |
| user | $user |
| checks from outside (thin client, no torch) | $checks |

Times are for layers not cached by an earlier run (with every image removed first, a clean build).
EOF
say "report: $report"
