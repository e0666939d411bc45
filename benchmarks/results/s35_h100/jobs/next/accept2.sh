# The rest of issue 17's acceptance run (session 35 ran the rest: benchmarks/results/s35_h100/accept).
# usage: bash gpujob/accept2.sh PART GPU.
# A: the four-bar with every peer, 4096 and 16384 worlds in separate processes (one process of both timed out at
#    300 s), and the animatronic at 1024 worlds with SolverKamino's DVI.
# B: the robots, ladder32 and the animatronic at the sizes not yet run, without peers (one process per scene), then
#    the four-bar at 16384 alone and after 4096 in one process (session 35 saw 3.94e6 and 6.06e6 in two processes on
#    the same GPU).
cd /tmp/repo; export PYTHONPATH=/tmp/site:/tmp/repo PYTHONUNBUFFERED=1
P=$1; export CUDA_VISIBLE_DEVICES=$2 WARP_CACHE_PATH=/tmp/wc_$1 JAX_COMPILATION_CACHE_DIR=/tmp/jc_$1 XLA_PYTHON_CLIENT_PREALLOCATE=false
R=/tmp/accept; mkdir -p $R; t0=$SECONDS
run() {  # NAME TIMEOUT args...
  local n=$1 t=$2; shift 2
  timeout $t python3 benchmarks/throughput.py --configs default --closure-steps 50 --repeats 3 --no-progress "$@" --out $R/$n.json > $R/$n.log 2>&1
  echo "$n rc $? at $((SECONDS-t0)) s" >> $R/steps_$P.txt
}
if [ $P = A ]; then
  run fourbar_4096 330 --scenes fourbar --worlds 4096 --replays 3
  run fourbar_16384 330 --scenes fourbar --worlds 16384 --replays 3
  # SolverKamino's dense Delassus buffer exceeds int32 indexing at 4096 animatronic worlds (session 35); 1024 fit
  run animatronic_1024 300 --scenes animatronic --worlds 1024 --replays 2 --kamino-variants dvi
else
  for s in dr_legs bdx olaf; do run sizes_$s 240 --scenes $s --worlds 1024 16384 65536 --replays 2 --no-peers; done
  run sizes_ladder32 150 --scenes ladder32 --worlds 65536 --replays 2 --no-peers
  run sizes_animatronic 300 --scenes animatronic --worlds 16384 65536 --replays 2 --no-peers
  run fourbar_16384_alone 90 --scenes fourbar --worlds 16384 --replays 3 --no-peers
  run fourbar_4096_16384 120 --scenes fourbar --worlds 4096 16384 --replays 3 --no-peers
fi
echo "part $P done at $((SECONDS-t0)) s" >> $R/steps_$P.txt
