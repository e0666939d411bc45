# quiet watch: sleep $1 s (or until the deadline has passed and every part is done), then one status line per run
# and collect into $OUT: L3's records and newest checkpoint, and the acceptance folder.
END=$(( $(date +%s) + $1 ))
while [ $(date +%s) -lt $END ]; do
  [ $(ls /tmp/accept/steps_*.txt 2>/dev/null | xargs -r grep -l "done" | wc -l) -ge 4 ] && [ $(date +%s) -ge $(cat /tmp/deadline) ] && break
  sleep 5
done
f=/tmp/rl_L3/train.log; [ -f $f ] && echo "L3: $(tail -c 3000 $f | tr '\r' '\n' | grep -a "env_steps" | tail -n 1 | cut -c1-120)"
cat /tmp/accept/steps_*.txt 2>/dev/null | tr '\n' ';'; echo
mkdir -p $OUT; D=/tmp/rl_L3
rm -rf /tmp/col; mkdir -p /tmp/col/L3
cp $D/*.json $D/*.txt $D/*.png /tmp/col/L3/ 2>/dev/null; tail -c 20000 $D/train.log > /tmp/col/L3/train_tail.log 2>/dev/null
last=$(ls $D/checkpoints 2>/dev/null | sort -n | tail -n 1)
[ -n "$last" ] && mkdir -p /tmp/col/L3/checkpoints && cp -r $D/checkpoints/$last /tmp/col/L3/checkpoints/
(cd /tmp/col && tar -czf $OUT/L3.tgz L3)
[ -d /tmp/accept ] && (cd /tmp && tar -czf $OUT/accept.tgz accept)
echo "deadline in $(( $(cat /tmp/deadline) - $(date +%s) )) s"
