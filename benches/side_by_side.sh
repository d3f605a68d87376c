#!/usr/bin/env bash
# Times the fullres networks in dsgs and, when a Python with PyTorch is available, the same passes
# in PyTorch, in one run, so the two can be compared on the same machine state.
#   benches/side_by_side.sh [PYTHON]     (default: $DSGS_TORCH_PYTHON, then python3)
# PyTorch is optional; without it only the dsgs figures are printed.
set -euo pipefail
cd "$(dirname "$0")/.."
py="${1:-${DSGS_TORCH_PYTHON:-python3}}"
cargo bench -p nets --bench networks
if "$py" -c "import torch" 2>/dev/null; then
  "$py" benches/torch_networks.py 2
else
  echo "PyTorch not found for $py: skipping the PyTorch side" >&2
fi
