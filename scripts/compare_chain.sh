#!/usr/bin/env bash
# Run a short campaign chain (calibrate -> ingest -> masks -> fit -> views -> prior ->
# refine -> fit2 -> mesh -> evaluate) on one session with the code of CHECKOUT, then
# compare every output file against a reference run's, byte for byte, timing fields
# aside (surfphase.bench.compare: TIMING_KEYS). Shows that a restructuring changed no
# output.
#
#   scripts/compare_chain.sh CHECKOUT CAMPAIGN STORE LABEL [REFERENCE_LABEL]
#
#   CHECKOUT   the source tree whose surfphase package and Snakefile run the chain
#   CAMPAIGN   a synthetic campaign (surfphase synth --preset demo --out CAMPAIGN)
#   STORE      scratch folder: STORE/work is where every chain runs (one fixed path, so
#              that paths recorded in the outputs agree), STORE/LABEL keeps its results
#   LABEL      name of this run's results under STORE
#   REFERENCE_LABEL  an earlier run under STORE to compare against (omit: no comparison)
#
# Environment: PYTHON (default python; it needs snakemake and the project's packages),
# THREADS (default 1), FRAMES (session01's frame range, default 12:18: a merge, a new
# bubble), COMPARE_WITH (the checkout whose surfphase.bench.compare compares, default
# CHECKOUT). The chain's sheet is written as CAMPAIGN/sessions_chain.tsv.
#
# Excluded from the comparison, and printed: the timing keys/columns of TIMING_KEYS,
# the folders logs/, benchmarks/, .snakemake/, and the "key" of the checkpoint states
# (fit.ckpt/state*.pt, fit2.ckpt/state*.pt): a hash of the parameters, inputs and the
# fit's source code, which changes with any edit of that code by design (a checkpoint of
# other code is not resumed); every other value in those states is compared.
set -euo pipefail

if [ $# -lt 4 ]; then
    sed -n 2,26p "$0"
    exit 2
fi
CHECKOUT=$(cd "$1" && pwd)
CAMPAIGN=$(cd "$2" && pwd)
STORE=$3
LABEL=$4
REF=${5:-}
PYTHON=${PYTHON:-python}
THREADS=${THREADS:-1}
FRAMES=${FRAMES:-12:18}
COMPARE_WITH=$(cd "${COMPARE_WITH:-$CHECKOUT}" && pwd)

mkdir -p "$STORE"
STORE=$(cd "$STORE" && pwd)
WORK=$STORE/work
rm -rf "$WORK"
mkdir -p "$WORK/config"

# One session, a few frames; the sheet sits in the campaign folder, whose paths it uses.
"$PYTHON" - "$CAMPAIGN" "$FRAMES" <<'EOF'
import sys
from pathlib import Path

import pandas as pd

campaign, frames = Path(sys.argv[1]), sys.argv[2]
df = pd.read_csv(campaign / "sessions.tsv", sep="\t", dtype=str, keep_default_na=False)
df = df[df["session"] == "session01"].copy()
df["frames"] = frames
df.to_csv(campaign / "sessions_chain.tsv", sep="\t", index=False)
EOF

cat >"$WORK/config/config.yaml" <<EOF
sessions: $CAMPAIGN/sessions_chain.tsv
rigs: $CAMPAIGN/rigs.tsv
results: results
device: cpu
threads: $THREADS
ingest: {scale: 0.25}
fit: {iters_first: 90, iters_next: 20}  # 90: densification refines at step 50
fit2: {iters_first: 10, iters_next: 20}
prior: {clips: $CAMPAIGN/clips, embedded: {steps: 20}}
refine: {enabled: true, n_views: 5}
mesh: {voxels: 32, n_orbit: 5}
report: {videos: false}
EOF

export PYTHONPATH=$CHECKOUT
export OMP_NUM_THREADS=$THREADS MKL_NUM_THREADS=$THREADS
start=$(date +%s)
if ! "$PYTHON" -m snakemake -s "$CHECKOUT/Snakefile" -d "$WORK" --cores "$THREADS" \
    --forceall results/session01/evaluate/metrics.json >"$STORE/$LABEL.log" 2>&1; then
    tail -n 40 "$STORE/$LABEL.log"
    echo "chain failed with $CHECKOUT (log: $STORE/$LABEL.log, job logs: $WORK/logs)"
    exit 1
fi
echo "chain with $CHECKOUT: $(($(date +%s) - start)) s, $THREADS thread(s), frames $FRAMES"
rm -rf "${STORE:?}/$LABEL"
mv "$WORK/results" "$STORE/$LABEL"
mv "$WORK/logs" "$STORE/$LABEL.logs"
[ -n "$REF" ] || exit 0

PYTHONPATH=$COMPARE_WITH "$PYTHON" - "$STORE/$REF" "$STORE/$LABEL" <<'EOF'
import sys
from pathlib import Path

from surfphase.bench.compare import TIMING_KEYS, compare_trees, same_file

ref, new = Path(sys.argv[1]), Path(sys.argv[2])
out = compare_trees(ref, new)
# Checkpoint states hold the run key (parameters, inputs, fit source code): compare
# everything else in them.
for rel in [r for r in out["differ"] if Path(r).name in ("state.pt", "state.prev.pt")]:
    if same_file(ref / rel, new / rel, TIMING_KEYS | {"key"}) is None:
        del out["differ"][rel]
        out["same"].append(rel + " (run key aside)")
print("timing fields excluded:", ", ".join(sorted(TIMING_KEYS)))
print("also excluded: logs/, benchmarks/, .snakemake/; 'key' of checkpoint state*.pt")
keyed = [r for r in out["same"] if r.endswith("(run key aside)")]
print(f"files compared: {len(out['same']) + len(out['differ'])} "
      f"({len(keyed)} checkpoint states compared without their run key)")
for rel, why in out["differ"].items():
    print(f"DIFFERS {rel}: {why}")
for rel in out["only_a"]:
    print(f"ONLY IN {ref.name}: {rel}")
for rel in out["only_b"]:
    print(f"ONLY IN {new.name}: {rel}")
bad = out["differ"] or out["only_a"] or out["only_b"]
print(f"{new.name} vs {ref.name}: " + ("NOT identical" if bad else "identical"))
sys.exit(1 if bad else 0)
EOF
