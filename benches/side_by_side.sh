#!/usr/bin/env bash
# Side-by-side speed figures measured in one run, so that each ratio compares numbers taken on the
# same machine state.
#
#   benches/side_by_side.sh nets [PYTHON] [ROUNDS]
#                                           the fullres networks in dsgs and, when a Python with
#                                           PyTorch is available (default: $DSGS_TORCH_PYTHON,
#                                           then python3), the same passes in PyTorch, both
#                                           with the dsgs binary's allocator setting. Each
#                                           pass runs on the dsgs side, then at once on the
#                                           PyTorch side (the two times of a ratio lie within a
#                                           minute), and prints one line:
#   nets <pass> round=<r> dsgs=<s> torch=<s> ratio=<x>
#                                           ROUNDS (default 1) repeats the four passes that
#                                           many times, then prints each pass's median ratio:
#   nets <pass> median ratio=<x> over <n> rounds (<lowest> to <highest>)
#   benches/side_by_side.sh raster [--quick] [--rounds N]
#                                           the rasterizer's vector lane kernels against its
#                                           scalar reference loops, forward and backward, on two
#                                           threads: 3, 35 and 64 channels at 100k Gaussians on
#                                           256x256 and 1M on 800x800 (--quick: 35 channels,
#                                           100k, 256x256 only). One line per case:
#   raster <channels>ch/<gaussians>/<size> <fwd|bwd> simd=<pairs/s> scalar=<pairs/s> ratio=<x>
#                                           --rounds N (default 1) runs the whole set N times,
#                                           each case's two kernels back to back in every round,
#                                           prints each round's lines with round=<r> after the
#                                           pass, then per case the line above for the round
#                                           whose ratio is the median (for an even N the lower
#                                           of the two middle ones), followed by
#                                           "median of <N> rounds (<lowest> to <highest>)".
#                                           On a machine whose speed drifts (a shared host), a
#                                           single run's two kernels can meet different
#                                           speeds; the median round's ratio is the steadier.
#   benches/side_by_side.sh train OLD_BINARY [--rounds N] [--quick]
#                                           the training loops of an earlier dsgs binary and of
#                                           this tree's (built here), alternating old and new in
#                                           every round (default 3 rounds), on the shared data:
#                                           pretrain-standard and pretrain-fullres (the WCT
#                                           relu3_1 pair, batch 8, 128-pixel crops),
#                                           features-fullres (lego 400x400, content and style
#                                           losses from the first iteration) and geometry (lego
#                                           200x200, resumed from one checkpoint of about 100k
#                                           Gaussians). Seconds per iteration are the difference
#                                           of the training-loop times two runs of K and 3K
#                                           iterations print, divided by 2K: set-up (reading
#                                           images, encoding views) is outside those times, and
#                                           what each loop does once (evaluations at its start
#                                           and end, the final save) cancels.
#                                           Each round prints
#   train <loop> round=<r> old=<s> new=<s> ratio=<old/new>
#                                           and at the end, per loop, the median round:
#   train <loop> old=<s> new=<s> ratio=<r> median of <n> rounds (<lowest> to <highest>)
#                                           --quick: one round with fewer iterations (a smoke
#                                           test of the script, not a figure). Inputs are made
#                                           once with the new binary under $DSGS_BENCH_DIR
#                                           (default ~/.cache/dsgs-bench): the imported networks
#                                           and the 7,000-iteration lego geometry (a few minutes).
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

# options MODE DEFAULT_ROUNDS ARGS...: sets $quick (--quick) and $rounds (--rounds N, a positive
# integer; DEFAULT_ROUNDS without it) from a mode's options, or exits naming a bad one.
options() {
  local mode="$1"
  quick=
  rounds="$2"
  shift 2
  while [ $# -gt 0 ]; do
    case "$1" in
    --quick) quick=yes ;;
    --rounds)
      if [ $# -lt 2 ]; then
        echo "--rounds needs a positive integer" >&2
        exit 2
      fi
      rounds="$2"
      shift
      ;;
    *)
      echo "unknown $mode option '$1' (expected --quick, --rounds N)" >&2
      exit 2
      ;;
    esac
    shift
  done
  case "$rounds" in
  '' | *[!0-9]* | 0)
    echo "--rounds needs a positive integer, got '$rounds'" >&2
    exit 2
    ;;
  esac
}

case "$what" in
nets)
  py="${1:-${DSGS_TORCH_PYTHON:-python3}}"
  rounds="${2:-1}"
  case "$rounds" in
  '' | *[!0-9]* | 0)
    echo "ROUNDS must be a positive integer, got '$rounds'" >&2
    exit 2
    ;;
  esac
  # Both sides run with the allocator setting of the dsgs binary (see the raster case below), so
  # that neither pays page faults for buffers the other keeps in its heap.
  export MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=2147483647
  torch=yes
  if ! "$py" -c "import torch" 2>/dev/null; then
    echo "PyTorch not found for $py: skipping the PyTorch side" >&2
    torch=
  fi
  log="$(mktemp)"
  ratios="$(mktemp)"
  trap 'rm -f "$log" "$ratios"' EXIT
  # The passes as "dsgs id:PyTorch name". Each pass runs on one side, then at once on the other,
  # so that both times of a ratio are taken within a minute of each other.
  passes="vgg_relu3_1_fullres_forward_256:encoder_relu3_1_fullres_256
vgg_relu4_1_fullres_forward_256:encoder_relu4_1_fullres_256
decoder_relu3_1_fullres_forward_256:decoder_relu3_1_fullres_256
decoder_relu3_1_fullres_forward_backward_256:decoder_relu3_1_fullres_forward_backward_256"
  cargo bench -q -p dsgs-nets --bench networks --no-run
  for r in $(seq 1 "$rounds"); do
    for pass in $passes; do
      ds="${pass%%:*}"
      ts="${pass##*:}"
      : >"$log"
      cargo bench -q -p dsgs-nets --bench networks -- "^networks/${ds}\$" | tee -a "$log"
      [ -n "$torch" ] || continue
      "$py" benches/torch_networks.py 2 "$ts" | tee -a "$log"
      # Criterion prints "networks/<id>" then "time: [low mid high]"; PyTorch "<name>\t<s>".
      awk -v round="$r" -v ds="$ds" -v ts="$ts" '
        function secs(v, unit) {
          if (unit == "ms") return v / 1e3
          if (unit ~ /^(µs|us)$/) return v / 1e6
          return v
        }
        /^networks\// { id = substr($1, 10) }
        /time:/ && id == ds {
          gsub(/[\[\]]/, "")
          for (i = 1; i <= NF; i++) if ($i == "time:") { d = secs($(i + 3), $(i + 4)) }
          id = ""
        }
        $0 ~ "^" ts "\t" { split($0, f, "\t"); t = f[2] }
        END {
          if (d == "" || t == "") exit
          printf "nets %s round=%d dsgs=%.4f torch=%.4f ratio=%.2f\n", ds, round, d, t, d / t
        }' "$log" | tee -a "$ratios"
    done
  done
  # With several rounds, each pass's median ratio.
  if [ -n "$torch" ] && [ "$rounds" -gt 1 ]; then
    for pass in $passes; do
      ds="${pass%%:*}"
      { grep "^nets $ds " "$ratios" || true; } | sed 's/.*ratio=//' | sort -g | awk -v ds="$ds" '
        { v[NR] = $1 }
        END {
          if (NR == 0) exit
          m = NR % 2 ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2
          printf "nets %s median ratio=%.2f over %d rounds (%s to %s)\n", ds, m, NR, v[1], v[NR]
        }'
    done
  fi
  ;;
raster)
  options raster 1 "$@"
  if [ -n "$quick" ]; then
    cases="35ch/100k/256"
  else
    cases="3ch/100k/256 35ch/100k/256 64ch/100k/256 3ch/1000k/800 35ch/1000k/800 64ch/1000k/800"
  fi
  log="$(mktemp)"
  lines="$(mktemp)"
  trap 'rm -f "$log" "$lines"' EXIT
  export MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=2147483647 MALLOC_ARENA_MAX=1
  cargo bench -q -p dsgs-raster --bench raster --no-run 2>/dev/null
  for r in $(seq 1 "$rounds"); do
    : >"$log"
    for c in $cases; do
      cargo bench -q -p dsgs-raster --bench raster -- "/$c/t2" 2>/dev/null | tee -a "$log" >/dev/null
    done
    # Criterion prints the id on one line and "thrpt: [low mid high]" two lines later.
    awk -v round="$r" -v rounds="$rounds" '
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
          if (rounds == 1) {
            printf "raster %s simd=%.4g scalar=%.4g ratio=%.2f\n", k, s, c, s / c
          } else {
            printf "raster %s round=%d simd=%.4g scalar=%.4g ratio=%.2f\n", k, round, s, c, s / c
          }
        }
      }' "$log" | tee -a "$lines"
  done
  # With several rounds, each case's median round.
  if [ "$rounds" -gt 1 ]; then
    awk '
      {
        key = $2 " " $3
        for (i = 4; i <= NF; i++) {
          split($i, kv, "=")
          f[kv[1]] = kv[2]
        }
        if (!(key in count)) order[++n] = key
        c = ++count[key]
        ratio[key, c] = f["ratio"] + 0
        line[key, c] = sprintf("simd=%s scalar=%s ratio=%s", f["simd"], f["scalar"], f["ratio"])
      }
      END {
        for (i = 1; i <= n; i++) {
          k = order[i]; m = count[k]
          # Insertion sort of the rounds by ratio (a handful of rounds).
          for (a = 1; a <= m; a++) idx[a] = a
          for (a = 2; a <= m; a++) {
            x = idx[a]
            for (b = a - 1; b >= 1 && ratio[k, idx[b]] > ratio[k, x]; b--) idx[b + 1] = idx[b]
            idx[b + 1] = x
          }
          mid = idx[int((m + 1) / 2)]
          printf "raster %s %s median of %d rounds (%.2f to %.2f)\n", k, line[k, mid], m,
            ratio[k, idx[1]], ratio[k, idx[m]]
        }
      }' "$lines"
  fi
  ;;
train)
  if [ $# -lt 1 ]; then
    echo "usage: benches/side_by_side.sh train OLD_BINARY [--rounds N] [--quick]" >&2
    exit 2
  fi
  old="$1"
  shift
  if [ ! -x "$old" ]; then
    echo "OLD_BINARY '$old' is not an executable file" >&2
    exit 2
  fi
  old="$(cd "$(dirname "$old")" && pwd)/$(basename "$old")"
  options train 3 "$@"
  [ -n "$quick" ] && rounds=1
  shared="${DSGS_SHARED:-../shared}"
  if [ ! -d "$shared/data/scenes/lego" ]; then
    echo "the shared data is not at '$shared' (set DSGS_SHARED)" >&2
    exit 2
  fi
  shared="$(cd "$shared" && pwd)"
  cargo build --release -q --bin dsgs
  new="$PWD/target/release/dsgs"
  work="${DSGS_BENCH_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/dsgs-bench}"
  mkdir -p "$work"
  work="$(cd "$work" && pwd)"
  runs="$(mktemp -d)"
  lines="$(mktemp)"
  trap 'rm -rf "$runs" "$lines"' EXIT
  wct="$shared/weights/wct-relu1_1-3_1"
  nets="$work/wct-relu3_1.safetensors"
  if [ ! -f "$nets" ]; then
    "$new" weights import --encoder "$wct/vgg_normalised_conv3_1.pth" \
      --decoder "$wct/feature_invertor_conv3_1.pth" -o "$nets" >/dev/null
  fi
  lego="$shared/data/scenes/lego"
  geo_iters=7000
  geo="$work/lego-200-geometry"
  if [ ! -f "$geo/chkpnt_$geo_iters.safetensors" ]; then
    echo "making the lego 200x200 geometry once ($geo_iters iterations, a few minutes)" >&2
    rm -rf "$geo"
    "$new" fit-geometry "$lego" --white --downscale 4 --iterations "$geo_iters" \
      --checkpoint-iterations "$geo_iters" --no-progress -o "$geo" >/dev/null
  fi
  if [ -n "$quick" ]; then
    k_pretrain=2 k_fullres=1 k_features=2 k_geometry=20
  else
    k_pretrain=10 k_fullres=4 k_features=10 k_geometry=200
  fi
  # One run of loop $1 with binary $2 for $3 iterations into $4.
  run_loop() {
    local loop="$1" bin="$2" k="$3" out="$4"
    case "$loop" in
    pretrain-standard | pretrain-fullres)
      "$bin" pretrain-decoder --weights "$nets" --content "$shared/data/pretrain/content" \
        --style "$shared/data/pretrain/styles" --recursive --variant "${loop#pretrain-}" \
        --iterations "$k" --batch-size 8 --crop 128 --checkpoint-every 0 --no-progress -o "$out"
      ;;
    features-fullres)
      # Earlier binaries name the dataset with --dataset rather than as an argument.
      local dataset=("$lego")
      if "$bin" fit-features --help | grep -q -- '--dataset <'; then
        dataset=(--dataset "$lego")
      fi
      "$bin" fit-features "${dataset[@]}" --white --downscale 2 --geometry "$geo/point_cloud.ply" \
        --style "$shared/data/styles/small-set" --weights "$nets" --variant fullres \
        --iterations "$k" --eval-every 0 --checkpoint-every 0 --no-encoding-cache \
        --no-progress -o "$out"
      ;;
    geometry)
      # $out is a fresh copy of the checkpoint's run (made before the clock starts).
      "$bin" fit-geometry "$lego" --white --downscale 4 --iterations "$((geo_iters + k))" \
        --resume "$out/chkpnt_$geo_iters.safetensors" --no-progress -o "$out"
      ;;
    esac
  }
  # Seconds per iteration of loop $1 with binary $2: runs of K and 3K iterations, timed.
  per_iteration() {
    local loop="$1" bin="$2" k="$3" t=() n
    for n in "$k" "$((3 * k))"; do
      local out="$runs/$loop-$n"
      rm -rf "$out"
      if [ "$loop" = geometry ]; then
        cp -r "$geo" "$out"
      fi
      if ! run_loop "$loop" "$bin" "$n" "$out" >"$runs/log" 2>&1; then
        echo "train $loop: $bin failed:" >&2
        tail -5 "$runs/log" >&2
        exit 1
      fi
      # The run's own closing line, "N iterations in S s (R it/s)": the training loop's wall
      # time, without the set-up before it (reading images, encoding views and styles).
      local secs
      secs="$(sed -n 's/.* iterations in \([0-9.]*\) s .*/\1/p' "$runs/log" | tail -1)"
      if [ -z "$secs" ]; then
        echo "train $loop: $bin printed no 'iterations in S s' line" >&2
        exit 1
      fi
      t+=("$secs")
      rm -rf "$out"
    done
    awk -v a="${t[0]}" -v b="${t[1]}" -v k="$k" 'BEGIN { printf "%.4f", (b - a) / (2 * k) }'
  }
  for r in $(seq 1 "$rounds"); do
    for loop in pretrain-standard pretrain-fullres features-fullres geometry; do
      case "$loop" in
      pretrain-standard) k="$k_pretrain" ;;
      pretrain-fullres) k="$k_fullres" ;;
      features-fullres) k="$k_features" ;;
      geometry) k="$k_geometry" ;;
      esac
      # Old first in odd rounds, new first in even ones.
      if [ $((r % 2)) -eq 1 ]; then
        o="$(per_iteration "$loop" "$old" "$k")"
        n="$(per_iteration "$loop" "$new" "$k")"
      else
        n="$(per_iteration "$loop" "$new" "$k")"
        o="$(per_iteration "$loop" "$old" "$k")"
      fi
      awk -v l="$loop" -v r="$r" -v o="$o" -v n="$n" \
        'BEGIN { printf "train %s round=%d old=%s new=%s ratio=%.2f\n", l, r, o, n, o / n }' |
        tee -a "$lines"
    done
  done
  if [ "$rounds" -gt 1 ]; then
    for loop in pretrain-standard pretrain-fullres features-fullres geometry; do
      grep "^train $loop " "$lines" | awk -v l="$loop" '
        {
          for (i = 3; i <= NF; i++) { split($i, kv, "="); f[kv[1]] = kv[2] }
          ratio[NR] = f["ratio"] + 0; line[NR] = sprintf("old=%s new=%s ratio=%s", f["old"], f["new"], f["ratio"])
          idx[NR] = NR
        }
        END {
          for (a = 2; a <= NR; a++) {
            x = idx[a]
            for (b = a - 1; b >= 1 && ratio[idx[b]] > ratio[x]; b--) idx[b + 1] = idx[b]
            idx[b + 1] = x
          }
          printf "train %s %s median of %d rounds (%.2f to %.2f)\n", l, line[idx[int((NR + 1) / 2)]],
            NR, ratio[idx[1]], ratio[idx[NR]]
        }'
    done
  fi
  ;;
*)
  echo "usage: benches/side_by_side.sh nets [PYTHON] [ROUNDS] | raster [--quick] [--rounds N] | train OLD_BINARY [--rounds N] [--quick]" >&2
  exit 2
  ;;
esac
