# watch p4 for $1 s (or until it is done), one line a minute
END=$(( $(date +%s) + $1 ))
while :; do
  echo "== $(date +%T)"; tail -n 2 /tmp/p4/steps.txt 2>/dev/null
  grep -q "p4 done" /tmp/p4/steps.txt 2>/dev/null && break
  [ $(date +%s) -ge $END ] && break
  sleep 30
done
