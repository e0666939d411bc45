# Session 37's second machine (the first went back between calls): the rest of issue 17's acceptance run on the
# timed-window rule, as accept3.sh but split over three GPUs. usage: bash gpujob/accept4.sh PART GPU
cd /tmp/repo; export PYTHONPATH=/tmp/site:/tmp/repo PYTHONUNBUFFERED=1
P=$1; export CUDA_VISIBLE_DEVICES=$2 WARP_CACHE_PATH=/tmp/wc_$1 JAX_COMPILATION_CACHE_DIR=/tmp/jc_$1 XLA_PYTHON_CLIENT_PREALLOCATE=false
R=/tmp/accept; mkdir -p $R; t0=$SECONDS
nvidia-smi -L > $R/gpus_$P.txt
run() {  # NAME TIMEOUT args...
  local n=$1 t=$2; shift 2
  timeout $t python3 benchmarks/throughput.py --configs default --closure-steps 120 --repeats 3 --no-progress "$@" --out $R/$n.json > $R/$n.log 2>&1
  echo "$n rc $? at $((SECONDS-t0)) s" >> $R/steps_$P.txt
}
case $P in
  Z) run sizes_ladder32 300 --scenes ladder32 --worlds 1024 16384 65536 --no-peers ;;
  A) run ladder8_4096 330 --scenes ladder8 --worlds 4096
     run ladder8_16384 250 --scenes ladder8 --worlds 16384 --kamino-variants padmm_dense
     for s in fourbar ladder8; do run sizes_$s 150 --scenes $s --worlds 1024 65536 --no-peers; done ;;
  B) run animatronic_1024 300 --scenes animatronic --worlds 1024 --replays 3 --kamino-variants dvi
     run animatronic_4096 240 --scenes animatronic --worlds 4096 --kamino-variants dvi
     run sizes_animatronic 300 --scenes animatronic --worlds 16384 65536 --no-peers ;;
  C) for s in bdx olaf; do run ${s}_4096 240 --scenes $s --worlds 4096 --kamino-variants dvi; done
     for s in dr_legs bdx olaf; do run sizes_$s 150 --scenes $s --worlds 1024 16384 65536 --no-peers; done ;;
esac
echo "part $P done at $((SECONDS-t0)) s" >> $R/steps_$P.txt
