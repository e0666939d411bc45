# watch for $1 s, one line a minute, then collect into $OUT (at most 8 files): per training run its records and
# newest checkpoint, and the acceptance run's folder. Every call collects, so a machine that goes back loses little.
END=$(( $(date +%s) + $1 ))
RUNS="L3 S3 L1 W3"
while :; do
  echo "== $(date +%T) deadline in $(( $(cat /tmp/deadline) - $(date +%s) )) s"
  for n in $RUNS; do f=/tmp/rl_$n/train.log; [ -f $f ] && echo "$n: $(tail -c 3000 $f | tr '\r' '\n' | grep -a "env_steps" | tail -n 1 | cut -c1-160)"; done
  tail -qn 1 /tmp/accept/steps_*.txt 2>/dev/null
  left=$(( END - $(date +%s) )); [ $left -le 0 ] && break
  sleep $(( left < 60 ? left : 60 ))
done
mkdir -p $OUT
for n in $RUNS; do
  D=/tmp/rl_$n; [ -d $D ] || continue
  rm -rf /tmp/col/$n; mkdir -p /tmp/col/$n
  cp $D/*.json $D/*.txt $D/*.png /tmp/col/$n/ 2>/dev/null; tail -c 20000 $D/train.log > /tmp/col/$n/train_tail.log
  last=$(ls $D/checkpoints 2>/dev/null | sort -n | tail -n 1)
  [ -n "$last" ] && mkdir -p /tmp/col/$n/checkpoints && cp -r $D/checkpoints/$last /tmp/col/$n/checkpoints/
  (cd /tmp/col && tar -czf $OUT/$n.tgz $n)
done
[ -d /tmp/accept ] && (cd /tmp && tar -czf $OUT/accept.tgz accept)
ls -la $OUT
