# watch quietly for $1 s, then print one line per run and collect into $OUT (per run: its records and newest
# checkpoint). With a second argument "eval" (the last call): once training has stopped, issue 18's walking test on
# L3's and L3s's newest checkpoints (256 episodes of 10 s, seed 0, rl_eval.py) before collecting.
END=$(( $(date +%s) + $1 )); RUNS="L3 L3s S3 C1"
while [ $(date +%s) -lt $END ]; do sleep 5; done
if [ "$2" = eval ]; then
  cd /tmp/repo; export PYTHONPATH=/tmp/site:/tmp/repo PYTHONUNBUFFERED=1
  while pgrep -f rl_train.py > /dev/null; do sleep 2; done
  i=0; for n in L3 L3s; do
    CUDA_VISIBLE_DEVICES=$i WARP_CACHE_PATH=/tmp/wc_$n timeout 200 python3 benchmarks/rl_eval.py /tmp/rl_$n \
      --backend warp --episodes 256 --seconds 10 --seed 0 --out /tmp/rl_$n/walk256.json > /tmp/rl_$n/walk256.log 2>&1 &
    i=$((i + 1)); done; wait
fi
for n in $RUNS; do f=/tmp/rl_$n/train.log; [ -f $f ] && echo "$n: $(tail -c 3000 $f | tr '\r' '\n' | grep -a env_steps | tail -n 1 | cut -c1-100)"; done
mkdir -p $OUT
for n in $RUNS; do
  D=/tmp/rl_$n; [ -d $D ] || continue
  rm -rf /tmp/col/$n; mkdir -p /tmp/col/$n
  cp $D/*.json $D/*.txt $D/*.log /tmp/col/$n/ 2>/dev/null; rm -f /tmp/col/$n/train.log
  tail -c 20000 $D/train.log > /tmp/col/$n/train_tail.log 2>/dev/null
  last=$(ls $D/checkpoints 2>/dev/null | sort -n | tail -n 1)
  [ -n "$last" ] && mkdir -p /tmp/col/$n/checkpoints && cp -r $D/checkpoints/$last /tmp/col/$n/checkpoints/
  (cd /tmp/col && tar -czf $OUT/$n.tgz $n)
done
echo "deadline in $(( $(cat /tmp/deadline) - $(date +%s) )) s"
