mkdir -p $OUT; (cd /tmp && tar -czf $OUT/p4.tgz p4); cat /tmp/p4/steps.txt; tail -n 3 /tmp/p4/gputests.log
