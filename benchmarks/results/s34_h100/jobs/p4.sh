# session 34 (an nvidia-h100-x1, after two x4 machines went back idle): the gpu tests, then issue 17's acceptance run
# (kamino at the defaults beside MuJoCo Warp and Newton SolverKamino), one process per scene and size, most needed first.
cd /tmp/repo; source gpujob/env.sh
export XLA_PYTHON_CLIENT_PREALLOCATE=false
R=/tmp/p4; rm -rf $R; mkdir -p $R; t0=$SECONDS
nvidia-smi -L > $R/gpus.txt
timeout 200 python3 -m pytest -m gpu -q -p no:cacheprovider > $R/gputests.log 2>&1; echo "gpu tests rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
run() {  # NAME TIMEOUT args...
  local n=$1 t=$2; shift 2
  timeout $t python3 benchmarks/throughput.py --configs default --closure-steps 50 --repeats 3 --no-progress "$@" --out $R/$n.json > $R/$n.log 2>&1
  echo "$n rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
}
run dr_legs_4096 480 --scenes dr_legs --worlds 4096 --replays 3
run ladder32_4096 480 --scenes ladder32 --worlds 4096 --replays 3
for s in fourbar ladder8; do run ${s}_4096 240 --scenes $s --worlds 4096 --replays 3; done
run animatronic_4096 240 --scenes animatronic --worlds 4096 --replays 2 --kamino-variants dvi
for s in bdx olaf; do run ${s}_4096 240 --scenes $s --worlds 4096 --replays 3 --kamino-variants dvi; done
for s in fourbar ladder8; do run ${s}_16384 240 --scenes $s --worlds 16384 --replays 3; done
run sizes_kamino 300 --scenes fourbar ladder8 ladder32 dr_legs bdx olaf --worlds 1024 16384 65536 --replays 2 --no-peers
echo "p4 done at $((SECONDS-t0)) s" >> $R/steps.txt
