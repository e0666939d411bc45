# Session 37's second machine: L3 (F25 at a fixed 3e-4, resumed from its 136.3 M checkpoint of the first machine)
# on GPU 0 after sizes_ladder32; the rest of the acceptance run on GPUs 1-3 (accept4.sh). Training until now + $1 s;
# then a quiet watch for $2 s. usage: bash gpujob/launch2.sh TRAIN_S WATCH_S
TRAIN_S=$1; WATCH_S=$2
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + TRAIN_S )); echo $DEADLINE > /tmp/deadline
T=benchmarks/results/s35_h100/jobs/next/train.sh
rm -rf /tmp/rl_L3; mkdir -p /tmp/rl_L3; cp -r gpujob/L3/* /tmp/rl_L3/
RWY="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}"
setsid nohup bash -c "bash gpujob/accept4.sh Z 0; bash $T L3 0 $DEADLINE --env \"$RWY\" --env gait_frequency=2.5 --set learning_rate_schedule=None" > /tmp/L3.out 2>&1 < /dev/null &
for p in A:1 B:2 C:3; do setsid nohup bash gpujob/accept4.sh ${p%:*} ${p#*:} > /tmp/acc_${p%:*}.out 2>&1 < /dev/null & done
bash gpujob/watch2.sh $WATCH_S
