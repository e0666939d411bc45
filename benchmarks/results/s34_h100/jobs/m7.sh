# session 34, GPU 3, part 1: the gpu tests on this tree, then throughput at 4096 worlds of the tree before the hubs
# and the 18 per-row vectors (/tmp/stage/c4/old2.tgz = f59b292) and of this tree, one after the other on the same
# GPU; the four-bar and ladder8 also at 16384; then the memory pool per world of every scene.
cd /tmp/repo; source gpujob/env.sh
export CUDA_VISIBLE_DEVICES=3 WARP_CACHE_PATH=/tmp/wc_M JAX_COMPILATION_CACHE_DIR=/tmp/jc_M XLA_PYTHON_CLIENT_PREALLOCATE=false
R=/tmp/m7; rm -rf $R; mkdir -p $R
nvidia-smi -L > $R/gpus.txt
t0=$SECONDS
timeout 150 python3 -m pytest -m gpu -x -q -p no:cacheprovider > $R/gputests.log 2>&1; echo "gpu tests rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
rm -rf /tmp/old && mkdir -p /tmp/old && tar -xzf /tmp/stage/c4/old2.tgz -C /tmp/old
TP="--scenes fourbar ladder8 dr_legs bdx olaf animatronic --worlds 4096 --configs default --closure-steps 50 --replays 3 --repeats 3 --no-peers --no-progress"
T2="--scenes fourbar ladder8 --worlds 16384 --configs default --closure-steps 50 --replays 3 --repeats 3 --no-peers --no-progress"
(cd /tmp/old && PYTHONPATH=/tmp/site:/tmp/old timeout 300 python3 benchmarks/throughput.py $TP --out $R/tp_old.json > $R/tp_old.log 2>&1); echo "old rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
timeout 300 python3 benchmarks/throughput.py $TP --out $R/tp_new.json > $R/tp_new.log 2>&1; echo "new rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
(cd /tmp/old && PYTHONPATH=/tmp/site:/tmp/old timeout 90 python3 benchmarks/throughput.py $T2 --out $R/tp16_old.json > $R/tp16_old.log 2>&1); echo "16k old rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
timeout 90 python3 benchmarks/throughput.py $T2 --out $R/tp16_new.json > $R/tp16_new.log 2>&1; echo "16k new rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
timeout 120 python3 benchmarks/memory_breakdown.py --scenes fourbar ladder8 ladder32 dr_legs bdx olaf animatronic --worlds 4096 --out $R/mem_new.json > $R/mem_new.log 2>&1; echo "memory rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
python3 - <<'PY' > $R/summary.txt 2>&1
import json
R = "/tmp/m7"
def rd(f):
    try: return json.load(open(f"{R}/{f}"))["records"]
    except Exception as e: print(f, e); return []
old = {(r["scene"], r["num_worlds"]): r for r in rd("tp_old.json") + rd("tp16_old.json")}
for r in rd("tp_new.json") + rd("tp16_new.json"):
    a = old.get((r["scene"], r["num_worlds"]), {})
    print(r["scene"], r["num_worlds"], "old %.3e new %.3e" % (a.get("throughput", 0), r["throughput"]), "mem %.0f -> %.0f" % (a.get("memory_per_world_bytes", 0), r["memory_per_world_bytes"]), "it", a.get("iterations_mean"), r["iterations_mean"], "closure %.2e conv %.3f" % (r["closure_max_m"], r["converged_fraction"]))
PY
grep -v "^W1\|^I1\|^ " $R/mem_new.log >> $R/summary.txt
tail -n 3 $R/gputests.log >> $R/summary.txt

