# session 34, GPU 2, beside m7.sh on GPU 3: issue 17's acceptance run, kamino at the defaults beside the peers (MuJoCo Warp, Newton
# SolverKamino) on every scene; one process per scene and size so that one hang loses one figure.
cd /tmp/repo; source gpujob/env.sh
export CUDA_VISIBLE_DEVICES=2 WARP_CACHE_PATH=/tmp/wc_P JAX_COMPILATION_CACHE_DIR=/tmp/jc_P XLA_PYTHON_CLIENT_PREALLOCATE=false
R=/tmp/p1; rm -rf $R; mkdir -p $R; t0=$SECONDS
run() {  # NAME TIMEOUT args...
  local n=$1 t=$2; shift 2
  timeout $t python3 benchmarks/throughput.py --configs default --closure-steps 50 --repeats 3 --no-progress "$@" --out $R/$n.json > $R/$n.log 2>&1
  echo "$n rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
}
for s in dr_legs ladder32 fourbar ladder8 bdx olaf; do run ${s}_4096 240 --scenes $s --worlds 4096 --replays 3; done
run animatronic_4096 300 --scenes animatronic --worlds 4096 --replays 2
for s in fourbar ladder8; do run ${s}_16384 240 --scenes $s --worlds 16384 --replays 3; done
run sizes_kamino 400 --scenes fourbar ladder8 ladder32 dr_legs bdx olaf --worlds 1024 16384 65536 --replays 2 --no-peers

