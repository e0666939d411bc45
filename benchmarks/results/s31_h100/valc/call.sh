# session 31 memory call: gpu tests on this tree (valc dropped: L_f stored once, the forward sweep's cent index
# loaded two columns ahead), then throughput at 4096 worlds of HEAD before the change (gpujob/old.tgz, 329ae17) and
# of this tree, same machine, one after the other; then the memory pool per world
source gpujob/env.sh
nvidia-smi -L > $OUT/gpus.txt
t0=$SECONDS
timeout 120 python3 -m pytest -m gpu -x -q -p no:cacheprovider > $OUT/gputests.log 2>&1; echo "gpu tests rc $? at $((SECONDS-t0)) s" >> $OUT/steps.txt
rm -rf /tmp/old && mkdir -p /tmp/old && tar -xzf gpujob/old.tgz -C /tmp/old
TP="--scenes fourbar ladder8 dr_legs bdx olaf --worlds 4096 --configs default --closure-steps 50 --replays 3 --repeats 3 --no-peers --no-progress"
(cd /tmp/old && PYTHONPATH=/tmp/site:/tmp/old timeout 150 python3 benchmarks/throughput.py $TP --out $OUT/tp_old.json > $OUT/tp_old.log 2>&1); echo "throughput old rc $? at $((SECONDS-t0)) s" >> $OUT/steps.txt
timeout 150 python3 benchmarks/throughput.py $TP --out $OUT/tp_new.json > $OUT/tp_new.log 2>&1; echo "throughput new rc $? at $((SECONDS-t0)) s" >> $OUT/steps.txt
timeout 60 python3 benchmarks/memory_breakdown.py --scenes fourbar ladder8 dr_legs bdx olaf animatronic --worlds 4096 --out $OUT/mem_new.json > $OUT/mem_new.log 2>&1; echo "memory rc $? at $((SECONDS-t0)) s" >> $OUT/steps.txt
T2="--scenes fourbar ladder8 --worlds 16384 --configs default --closure-steps 50 --replays 3 --repeats 3 --no-peers --no-progress"
(cd /tmp/old && PYTHONPATH=/tmp/site:/tmp/old timeout 60 python3 benchmarks/throughput.py $T2 --out $OUT/tp16_old.json > $OUT/tp16_old.log 2>&1); echo "16k old rc $? at $((SECONDS-t0)) s" >> $OUT/steps.txt
timeout 60 python3 benchmarks/throughput.py $T2 --out $OUT/tp16_new.json > $OUT/tp16_new.log 2>&1; echo "16k new rc $? at $((SECONDS-t0)) s" >> $OUT/steps.txt
cat $OUT/steps.txt; tail -n 3 $OUT/gputests.log
python3 - <<'PY'
import json, os
o = os.environ["OUT"]
def rd(f):
    try: return json.load(open(f"{o}/{f}"))["records"]
    except Exception as e: print(f, e); return []
old = {(r["scene"], r["num_worlds"]): r for r in rd("tp_old.json") + rd("tp16_old.json")}
for r in rd("tp_new.json") + rd("tp16_new.json"):
    a = old.get((r["scene"], r["num_worlds"]), {})
    print(r["scene"], r["num_worlds"], "old %.3e new %.3e" % (a.get("throughput", 0), r["throughput"]), "mem %.0f -> %.0f" % (a.get("memory_per_world_bytes", 0), r["memory_per_world_bytes"]), "it", a.get("iterations_mean"), r["iterations_mean"], "closure %.2e conv %.3f" % (r["closure_max_m"], r["converged_fraction"]))
PY
grep -v "^W1\|^I1\|^ " $OUT/mem_new.log
