#!/usr/bin/env bash
# Side-by-side speed figures measured in one run, so that each ratio compares numbers taken on the
# same machine state.
#
#   benches/side_by_side.sh nets [PYTHON]   the fullres networks in dsgs and, when a Python with
#                                           PyTorch is available (default: $DSGS_TORCH_PYTHON,
#                                           then python3), the same passes in PyTorch, both
#                                           with the dsgs binary's allocator setting
#   benches/side_by_side.sh raster [--quick]
#                                           the rasterizer's vector lane kernels against its
#                                           scalar reference loops, forward and backward, on two
#                                           threads: 3, 35 and 64 channels at 100k Gaussians on
#                                           256x256 and 1M on 800x800 (--quick: 35 channels,
#                                           100k, 256x256 only). One line per case:
#   raster <channels>ch/<gaussians>/<size> <fwd|bwd> simd=<pairs/s> scalar=<pairs/s> ratio=<x>
#
# Pairs/s are blended Gaussian-pixel pairs per second at criterion's point estimate. PyTorch is
# optional; without it only the dsgs network figures are printed.
#
# The raster cases run with the allocator setting the dsgs binary makes at start-up (freed
# memory stays in glibc's heap; see base::memory::keep_freed_memory), for both kernels, so that
# page faults of freshly mapped buffers do not hide the tile loops' speed. They also run with
# one glibc arena: criterion calls each pass inside `ThreadPool::install`, on a pool thread,
# whose own arena cannot hold blocks above 64 MiB, so glibc maps and unmaps them at every call
# (page faults and TLB shootdowns took a third of the 1M-Gaussian backward passes); the dsgs
# binary runs its commands on a pool thread too, and sets one arena at start-up.
set -euo pipefail
cd "$(dirname "$0")/.."
what="${1:-nets}"
shift || true

case "$what" in
nets)
  py="${1:-${DSGS_TORCH_PYTHON:-python3}}"
  # Both sides run with the allocator setting of the dsgs binary (see the raster case below), so
  # that neither pays page faults for buffers the other keeps in its heap.
  export MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=2147483647
  cargo bench -p dsgs-nets --bench networks
  if "$py" -c "import torch" 2>/dev/null; then
    "$py" benches/torch_networks.py 2
  else
    echo "PyTorch not found for $py: skipping the PyTorch side" >&2
  fi
  ;;
raster)
  if [ "${1:-}" = "--quick" ]; then
    cases="35ch/100k/256"
  else
    cases="3ch/100k/256 35ch/100k/256 64ch/100k/256 3ch/1000k/800 35ch/1000k/800 64ch/1000k/800"
  fi
  log="$(mktemp)"
  trap 'rm -f "$log"' EXIT
  export MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=2147483647 MALLOC_ARENA_MAX=1
  for c in $cases; do
    cargo bench -q -p dsgs-raster --bench raster -- "/$c/t2" 2>/dev/null | tee -a "$log" >/dev/null
  done
  # Criterion prints the id on one line and "thrpt: [low mid high]" two lines later.
  awk '
    function rate(v, unit) {
      if (unit ~ /^Gelem/) return v * 1e9
      if (unit ~ /^Melem/) return v * 1e6
      if (unit ~ /^Kelem/) return v * 1e3
      return v
    }
    /^(forward|backward)\/(scalar|simd)\// { id = $1 }
    /thrpt:/ && id != "" {
      gsub(/[\[\]]/, "")
      for (i = 1; i <= NF; i++) if ($i == "thrpt:") { v = $(i + 3); u = $(i + 4) }
      split(id, p, "/")
      key = p[3] "/" p[4] "/" p[5] " " (p[1] == "forward" ? "fwd" : "bwd")
      r[key, p[2]] = rate(v, u)
      if (!(key in seen)) { seen[key] = 1; order[++n] = key }
      id = ""
    }
    END {
      for (i = 1; i <= n; i++) {
        k = order[i]; s = r[k, "simd"]; c = r[k, "scalar"]
        if (s == "" || c == "") continue
        printf "raster %s simd=%.4g scalar=%.4g ratio=%.2f\n", k, s, c, s / c
      }
    }' "$log"
  ;;
*)
  echo "usage: benches/side_by_side.sh nets [PYTHON] | raster [--quick]" >&2
  exit 2
  ;;
esac
