# Session 38's job (planned in session 37): issue 18's walking policy, four runs at the config's fixed 3e-4 rate.
#   GPU 0, L3: resumed from benchmarks/results/s37_h100/L3 (161.9 M; error 0.144 m/s, no falls at 128 episodes)
#   GPU 1, L3s: the same checkpoint at 1e-4 (a smaller step near the end)
#   GPU 2, S3: resumed from benchmarks/results/s37_h100/S3 (12.8 M; the feet_width settings, its env.json)
#   GPU 3, C1: the config from scratch, seed 1 (does the recipe train without F25's history?)
# Training until now + $1 s; then watch (and collect) for $2 s. usage: bash gpujob/launch.sh TRAIN_S WATCH_S
TRAIN_S=$1; WATCH_S=$2
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + TRAIN_S )); echo $DEADLINE > /tmp/deadline
S=benchmarks/results/s37_h100; T=gpujob/train.sh
for n in L3 L3s S3 C1; do rm -rf /tmp/rl_$n; mkdir -p /tmp/rl_$n; done
for n in L3 L3s; do cp -r $S/L3/checkpoints $S/L3/*.json /tmp/rl_$n/; done
cp -r $S/S3/checkpoints $S/S3/*.json /tmp/rl_S3/
setsid nohup bash $T L3 0 $DEADLINE > /tmp/L3.out 2>&1 < /dev/null &
setsid nohup bash $T L3s 1 $DEADLINE --set learning_rate=1e-4 > /tmp/L3s.out 2>&1 < /dev/null &
setsid nohup bash $T S3 2 $DEADLINE > /tmp/S3.out 2>&1 < /dev/null &
setsid nohup bash $T C1 3 $DEADLINE --seed 1 > /tmp/C1.out 2>&1 < /dev/null &
bash gpujob/watch.sh $WATCH_S
