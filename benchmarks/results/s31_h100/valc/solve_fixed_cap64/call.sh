source /tmp/gj/env.sh
timeout 150 python3 benchmarks/throughput.py --scenes fourbar ladder8 --worlds 4096 16384 --configs default --closure-steps 50 --replays 3 --repeats 3 --no-peers --no-progress --out $OUT/tp_cap.json > $OUT/tp_cap.log 2>&1; echo rc $?
python3 -c "
import json; d=json.load(open('$OUT/tp_cap.json'))['records']
for r in d: print(r['scene'], r['num_worlds'], '%.3e'%r['throughput'], r['iterations_mean'], '%.2e'%r['closure_max_m'], r['converged_fraction'])"
f=$(ls -tr /root/.cache/warp/1.19.0/*/*solve_fixed_*.sm90.cubin | tail -3); for x in $f; do cuobjdump --dump-resource-usage $x | grep -o "REG:[0-9]*"; done
