# Session 37's third machine (one call after staging): the gpu tests and the animatronic's memory after the unread
# factor tables were dropped (sparse_llt.build(fan=...)), its 65536 worlds and olaf's, and L3 resumed from 149.1 M.
# Everything stops at now + $1 s and is collected into $OUT. usage: bash gpujob/launch3.sh SECONDS
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + $1 )); echo $DEADLINE > /tmp/deadline
T=benchmarks/results/s35_h100/jobs/next/train.sh
rm -rf /tmp/rl_L3; mkdir -p /tmp/rl_L3; cp -r gpujob/L3/* /tmp/rl_L3/
RWY="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}"
setsid nohup bash $T L3 3 $DEADLINE --env "$RWY" --env gait_frequency=2.5 --set learning_rate_schedule=None > /tmp/L3.out 2>&1 < /dev/null &
export PYTHONPATH=/tmp/site:/tmp/repo PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
R=/tmp/accept; mkdir -p $R
run() {  # GPU NAME args...: until the deadline at most
  local g=$1 n=$2; shift 2; local t=$(( DEADLINE - $(date +%s) )); [ $t -le 5 ] && return
  CUDA_VISIBLE_DEVICES=$g WARP_CACHE_PATH=/tmp/wc_$g JAX_COMPILATION_CACHE_DIR=/tmp/jc_$g timeout $t python3 \
    benchmarks/throughput.py --configs default --closure-steps 120 --repeats 3 --no-progress "$@" --out $R/$n.json > $R/$n.log 2>&1
  echo "$n rc $? at $(date +%T)" >> $R/steps_$g.txt
}
( CUDA_VISIBLE_DEVICES=0 timeout 200 python3 -m pytest -m gpu -q -p no:cacheprovider > $R/gputests.log 2>&1
  echo "gpu tests rc $? at $(date +%T)" >> $R/steps_0.txt
  run 0 animatronic_1024 --scenes animatronic --worlds 1024 --kamino-variants ) &
( run 1 animatronic_4096 --scenes animatronic --worlds 4096 --kamino-variants
  run 1 sizes_olaf_65536 --scenes olaf --worlds 65536 --no-peers ) &
( run 2 sizes_animatronic_65536 --scenes animatronic --worlds 65536 --no-peers ) &
while [ $(date +%s) -lt $DEADLINE ]; do sleep 3; done
sleep 2
f=/tmp/rl_L3/train.log; [ -f $f ] && echo "L3: $(tail -c 3000 $f | tr '\r' '\n' | grep -a "env_steps" | tail -n 1 | cut -c1-100)"
cat $R/steps_*.txt | tr '\n' ';'; echo
mkdir -p $OUT; D=/tmp/rl_L3; rm -rf /tmp/col; mkdir -p /tmp/col/L3
cp $D/*.json $D/*.txt /tmp/col/L3/ 2>/dev/null; tail -c 20000 $D/train.log > /tmp/col/L3/train_tail.log 2>/dev/null
last=$(ls $D/checkpoints 2>/dev/null | sort -n | tail -n 1)
[ -n "$last" ] && mkdir -p /tmp/col/L3/checkpoints && cp -r $D/checkpoints/$last /tmp/col/L3/checkpoints/
(cd /tmp/col && tar -czf $OUT/L3.tgz L3); (cd /tmp && tar -czf $OUT/accept.tgz accept)
