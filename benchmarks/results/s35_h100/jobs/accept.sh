# issue 17's acceptance run on GPU 3: the gpu tests, then kamino at the defaults beside MuJoCo Warp and Newton
# SolverKamino, one process per scene and size. SolverKamino's DVI (its faster variant on every robot, session 24)
# alone on the robots and ladder32: its PADMM needs about 400 s for dr_legs (session 34). ~17 min in all.
cd /tmp/repo; export PYTHONPATH=/tmp/site:/tmp/repo PYTHONUNBUFFERED=1
export CUDA_VISIBLE_DEVICES=3 WARP_CACHE_PATH=/tmp/wc_A JAX_COMPILATION_CACHE_DIR=/tmp/jc_A XLA_PYTHON_CLIENT_PREALLOCATE=false
R=/tmp/accept; rm -rf $R; mkdir -p $R; t0=$SECONDS
nvidia-smi -L > $R/gpus.txt
timeout 200 python3 -m pytest -m gpu -q -p no:cacheprovider > $R/gputests.log 2>&1; echo "gpu tests rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
run() {  # NAME TIMEOUT args...
  local n=$1 t=$2; shift 2
  timeout $t python3 benchmarks/throughput.py --configs default --closure-steps 50 --repeats 3 --no-progress "$@" --out $R/$n.json > $R/$n.log 2>&1
  echo "$n rc $? at $((SECONDS-t0)) s" >> $R/steps.txt
}
for s in fourbar ladder8; do run ${s} 300 --scenes $s --worlds 4096 16384 --replays 3; done
for s in dr_legs ladder32 bdx olaf; do run ${s} 240 --scenes $s --worlds 4096 --replays 3 --kamino-variants dvi; done
run animatronic 240 --scenes animatronic --worlds 4096 --replays 2 --kamino-variants dvi
run sizes 300 --scenes fourbar ladder8 ladder32 dr_legs bdx olaf animatronic --worlds 1024 16384 65536 --replays 2 --no-peers
echo "accept done at $((SECONDS-t0)) s" >> $R/steps.txt
