#!/usr/bin/env bash
# Builds the rfcl runtime images from the host's release binaries (Rust is not built in Docker: a
# 2-core machine takes minutes where copying takes seconds):
#   rfcl-curriculum:local  curriculum-server, rfcl-health
#   rfcl:local             learner, actor, rfcl, rfcl-health, configs at /opt/rfcl/configs, and only
#                          the libtorch CPU libraries the binaries load (ldd), in /opt/rfcl/lib
# Each image is built from its own small staging directory (target/docker-stage/IMAGE: binaries,
# libraries, configs, the Debian runtime packages the binaries link), never from the repository
# with its multi-GB .venv. Then every binary's --help runs inside its image, and ldd checks that
# nothing is missing there. Prints the time and size of each image. Idempotent: Docker's layer cache
# keeps unchanged layers, so a rebuild after `cargo build` replaces only the binaries' layer.
#
# The learner binary force-links libtorch_cuda.so (learner/build.rs, for --device cuda), which
# would pull 2.7 GB of CUDA libraries (cuBLAS, cuDNN, NCCL, ...) into the image. The CPU image's
# learner is a copy with that one DT_NEEDED entry removed (patchelf): the binary uses no symbol of
# it (ldd -r finds none undefined), exactly as a build with RFCL_LINK_CUDA=0.
#
# The binaries are copied with `strip --strip-debug` (the release profile's line tables are ~90 %
# of their size; symbols stay, so backtraces still name functions): --keep-debug keeps them.
#
# Usage: deploy/build-images.sh [--no-cache] [--keep-debug] [--cuda]
#   --cuda      also build rfcl-cuda:local: the learner as built, with libtorch_cuda and the NVIDIA
#               wheels' libraries it needs (3.7 GB; for a GPU host with the NVIDIA container toolkit)
# Needs: deploy/setup-docker.sh (docker, the base image) and scripts/setup.sh (the release build).
# Env: RFCL_IMAGE_TAG (default local), RFCL_VENV (default .venv)
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV=${RFCL_VENV:-$ROOT/.venv}
REL=$ROOT/target/release
STAGE_ROOT=$ROOT/target/docker-stage
TAG=${RFCL_IMAGE_TAG:-local}
NO_CACHE=(); CUDA=0; KEEP_DEBUG=0
for arg in "$@"; do
  case "$arg" in
    --keep-debug) KEEP_DEBUG=1 ;;
    --no-cache) NO_CACHE=(--no-cache) ;;
    --cuda) CUDA=1 ;;
    -h|--help) sed -n '2,25p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "build-images: unknown argument '$arg'" >&2; exit 2 ;;
  esac
done

step() { printf '==> %s\n' "$*"; }
note() { printf '    %s\n' "$*"; }
fail() { printf 'build-images: FAILED: %s\n' "$*" >&2; exit 1; }
mb() { awk -v b="$1" 'BEGIN { printf "%.0f MB", b / 1e6 }'; }
now() { date +%s.%N; }
secs() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.1f s", b - a }'; }

docker info >/dev/null 2>&1 || fail "no Docker daemon: run deploy/setup-docker.sh first"
docker image inspect debian:bookworm-slim >/dev/null 2>&1 \
  || fail "no debian:bookworm-slim base image: run deploy/setup-docker.sh first"
command -v patchelf >/dev/null || fail "no patchelf: run deploy/setup-docker.sh first"

# The Debian packages owning library paths, looked up with one dpkg -S call (ldd prints /lib/...
# or /usr/lib/..., and with merged /usr dpkg may have recorded either spelling). Fills OWNER.
declare -A OWNER=()
find_owners() {
  local p cands=() line pkg path
  for p in "$@"; do cands+=("$p" "$(readlink -f "$p")" "${p#/usr}" "/usr$p"); done
  while IFS= read -r line; do
    case "$line" in diversion*) continue ;; esac
    pkg=${line%%: *}; pkg=${pkg%%:*}; path=${line#*: }
    OWNER[$path]=$pkg
  done < <(dpkg -S "${cands[@]}" 2>/dev/null || true)
}
owner_pkg() {
  local p=$1 cand
  for cand in "$p" "$(readlink -f "$p")" "${p#/usr}" "/usr$p"; do
    [ -n "${OWNER[$cand]:-}" ] && { echo "${OWNER[$cand]}"; return 0; }
  done
  return 1
}

# stage IMAGE ROLE CPU_ONLY BIN... : fills target/docker-stage/IMAGE. A binary named with a
# trailing '?' is optional (skipped with a note when it is not built). CPU_ONLY=1 drops the
# learner's forced libtorch_cuda.so link (see above).
stage() {
  local image=$1 role=$2 cpu_only=$3; shift 3
  local dir=$STAGE_ROOT/$image
  rm -rf "$dir"; mkdir -p "$dir/bin" "$dir/lib" "$dir/configs"
  cp deploy/docker/Dockerfile "$dir/Dockerfile"
  local b name src bins=()
  for b in "$@"; do
    name=${b%\?}; src=$REL/$name
    if [ ! -x "$src" ]; then
      if [ "$name" != "$b" ]; then note "$name: not built yet, left out"; continue; fi
      fail "$src is missing: run scripts/setup.sh (or cargo build --release --workspace) first"
    fi
    cp "$src" "$dir/bin/$name"
    if [ $KEEP_DEBUG = 0 ]; then
      # The release profile's line tables are ~90 % of each binary; symbols stay (backtraces
      # still name functions).
      strip --strip-debug "$dir/bin/$name"
    fi
    if [ "$cpu_only" = 1 ] && readelf -d "$src" | grep -q 'NEEDED.*\[libtorch_cuda\.so\]'; then
      patchelf --remove-needed libtorch_cuda.so "$dir/bin/$name"
      if ldd -r "$dir/bin/$name" 2>&1 | grep -q 'undefined symbol'; then
        fail "$name uses libtorch_cuda symbols: it cannot go CPU-only (build with RFCL_LINK_CUDA=0, or --cuda)"
      fi
      note "$name: CPU-only (libtorch_cuda.so dropped from its DT_NEEDED; ldd -r: no undefined symbol)"
    fi
    bins+=("$dir/bin/$name")
  done
  cp -r configs/. "$dir/configs/"
  # Libraries, from ldd of every binary (transitively): those of Debian packages are installed
  # from Debian in the image (only the packages of libraries something staged needs directly:
  # apt brings their dependencies), the others (the venv's torch and nvidia wheels) are copied.
  local line lib path pkg missing=() system=() lddout
  declare -A where=()
  lddout=$(for b in "${bins[@]}"; do ldd "$b"; done | sort -u)
  find_owners $(sed -n 's/.*=> \(\/[^ ]*\) (.*/\1/p' <<<"$lddout")
  while read -r line; do
    case "$line" in
      *"=> not found"*) missing+=("${line%% *}"); continue ;;
      *"=> /"*) lib=${line%% =>*}; path=${line#*=> }; path=${path%% (*} ;;
      *) continue ;;  # vdso, the dynamic loader itself
    esac
    where[$lib]=$path
    if owner_pkg "$path" >/dev/null; then
      system+=("$lib")
    else
      ln -f "$(readlink -f "$path")" "$dir/lib/$lib" 2>/dev/null || cp -L "$path" "$dir/lib/$lib"
    fi
  done <<<"$lddout"
  [ ${#missing[@]} -eq 0 ] || fail "ldd finds no ${missing[*]} for the $image binaries (is $VENV the build's venv?)"
  if [ "$cpu_only" = 0 ] && [ -n "${where[libtorch_cuda.so]:-}" ]; then
    # What libtorch_cuda and cuDNN open with dlopen (ldd cannot see it): linalg (cuSOLVER), NVRTC,
    # cuDNN's sub-libraries; then those libraries' own dependencies.
    local torchlib nv extra extras=()
    torchlib=$(dirname "$(readlink -f "${where[libtorch_cuda.so]}")")
    nv=$(readlink -f "$torchlib/../../nvidia")
    for extra in "$torchlib"/libtorch_cuda_linalg.so "$torchlib"/libcaffe2_nvrtc.so \
                 "$nv"/cudnn/lib/libcudnn*.so.* "$nv"/*/lib/libnvrtc*.so* "$nv"/*/lib/libcusolver.so.* \
                 "$nv"/*/lib/libnvtx3interop.so.*; do
      [ -f "$extra" ] || continue
      extras+=("$extra")
      [ -e "$dir/lib/$(basename "$extra")" ] || ln -f "$extra" "$dir/lib/$(basename "$extra")" 2>/dev/null \
        || cp "$extra" "$dir/lib/$(basename "$extra")"
    done
    while read -r line; do
      case "$line" in *"=> /"*) lib=${line%% =>*}; path=${line#*=> }; path=${path%% (*} ;; *) continue ;; esac
      case "$(readlink -f "$path")" in
        "$(readlink -f "$VENV")"/*) [ -e "$dir/lib/$lib" ] || cp -L "$path" "$dir/lib/$lib" ;;
      esac
    done < <(ldd "${extras[@]}" 2>/dev/null | sort -u)
  fi
  local direct
  direct=$(for f in "${bins[@]}" "$dir"/lib/*; do if [ -f "$f" ]; then readelf -d "$f"; fi; done \
    | sed -n 's/.*(NEEDED).*\[\(.*\)\]/\1/p' | sort -u)
  : >"$dir/packages.txt"
  for lib in "${system[@]}"; do
    grep -qxF "$lib" <<<"$direct" || continue
    owner_pkg "${where[$lib]}" >>"$dir/packages.txt"
  done
  # libc6, libgcc-s1 and libstdc++6 are in the base image already.
  sort -u -o "$dir/packages.txt" "$dir/packages.txt"
  sed -i -E '/^(libc6|libgcc-s1|libstdc\+\+6)$/d' "$dir/packages.txt"
  note "binaries: $(cd "$dir/bin" && echo *)"
  note "Debian packages: $(tr '\n' ' ' <"$dir/packages.txt")"
  if compgen -G "$dir/lib/*" >/dev/null; then
    note "copied libraries: $(cd "$dir/lib" && for f in *; do printf '%s (%s) ' "$f" "$(mb "$(stat -c %s "$f")")"; done)"
  else
    note "copied libraries: none"
  fi
  echo "$role" >"$dir/.role"
}

# build IMAGE : docker build of the staged directory, then the in-image checks.
build() {
  local image=$1 dir=$STAGE_ROOT/$1 role t0 t1 size
  role=$(cat "$dir/.role")
  local old
  old=$(docker image inspect -f '{{.Id}}' "$image:$TAG" 2>/dev/null || true)
  t0=$(now)
  docker build "${NO_CACHE[@]}" -q --build-arg RFCL_ROLE="$role" -t "$image:$TAG" "$dir" >/dev/null 2>"$dir.build.log" \
    || { cat "$dir.build.log" >&2; fail "docker build $image:$TAG (log above)"; }
  t1=$(now)
  size=$(docker image inspect -f '{{.Size}}' "$image:$TAG")
  if [ -n "$old" ] && [ "$old" != "$(docker image inspect -f '{{.Id}}' "$image:$TAG")" ]; then
    # The image this one replaces, unless a container still uses it.
    docker rmi "$old" >/dev/null 2>&1 && note "removed the previous $image:$TAG (${old:7:12})" || true
  fi
  step "$image:$TAG built in $(secs "$t0" "$t1"), $(mb "$size")"
  # Checks inside the image: nothing unresolved, and every binary starts.
  local out
  out=$(docker run --rm --entrypoint sh "$image:$TAG" -c 'ldd /opt/rfcl/bin/* | grep "not found" || true')
  [ -z "$out" ] || fail "$image:$TAG: unresolved libraries inside the image: $out"
  local bin
  for bin in "$dir"/bin/*; do
    bin=$(basename "$bin")
    if [ "$bin" = rfcl-health ]; then
      # Its usage is ADDR; --help must still exit 0.
      docker run --rm "$image:$TAG" rfcl-health --help >/dev/null 2>&1 \
        || fail "$image:$TAG: rfcl-health --help fails"
    else
      docker run --rm "$image:$TAG" "$bin" --help >/dev/null 2>"$dir.check.log" \
        || { cat "$dir.check.log" >&2; fail "$image:$TAG: $bin --help fails inside the image"; }
    fi
  done
  note "checked inside the image: ldd resolves everything; --help runs for $(cd "$dir/bin" && echo *)"
  rm -f "$dir.build.log" "$dir.check.log"
}

T0=$(now)
step "staging rfcl-curriculum (target/docker-stage/rfcl-curriculum)"
stage rfcl-curriculum curriculum 1 curriculum-server 'rfcl-health?'
if [ -n "$(ls "$STAGE_ROOT/rfcl-curriculum/lib")" ]; then
  note "note: curriculum-server links libraries outside Debian (above): they are in the image"
fi
step "staging rfcl (target/docker-stage/rfcl)"
stage rfcl rfcl 1 learner actor rfcl 'rfcl-health?'

step "building rfcl-curriculum:$TAG"
build rfcl-curriculum
step "building rfcl:$TAG"
build rfcl

if [ $CUDA = 1 ]; then
  step "staging rfcl-cuda (target/docker-stage/rfcl-cuda)"
  stage rfcl-cuda cuda 0 learner actor rfcl 'rfcl-health?'
  step "building rfcl-cuda:$TAG"
  build rfcl-cuda
fi

step "images (built in $(secs "$T0" "$(now)") in all)"
docker image ls --format '{{.Repository}}:{{.Tag}}  {{.Size}}  created {{.CreatedSince}}' \
  | grep -E "^(rfcl|rfcl-curriculum|rfcl-cuda):$TAG " | sed 's/^/    /' || true
