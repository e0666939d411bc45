# Session 36's job (planned in session 35). GPUs 0-1: F25 and F25W resumed from session 35's checkpoints
# (benchmarks/results/s35_h100/*/checkpoints, in the tree). GPU 2: accept2.sh A (the four-bar with every peer), then
# F2W resumed. GPU 3: accept2.sh B (the robots at 1024/16384/65536 worlds, the four-bar's 16384 figure alone and
# after 4096), then F25toW: F25's 59.6 M checkpoint with the feet_width term added. Training until now + $1 s;
# then watch (and collect) for $2 s.
TRAIN_S=$1; WATCH_S=$2
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + TRAIN_S )); echo $DEADLINE > /tmp/deadline
S=benchmarks/results/s35_h100
for n in F25 F25W F2W; do rm -rf /tmp/rl_$n; mkdir -p /tmp/rl_$n; cp -r $S/$n/checkpoints $S/$n/*.json /tmp/rl_$n/; done
rm -rf /tmp/rl_F25toW; mkdir -p /tmp/rl_F25toW; cp -r $S/F25/checkpoints /tmp/rl_F25toW/
RWW="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05, 'feet_width': 0.5}"
RWY="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}"
setsid nohup bash gpujob/train.sh F25 0 $DEADLINE --env "$RWY" --env gait_frequency=2.5 > /tmp/F25.out 2>&1 < /dev/null &
setsid nohup bash gpujob/train.sh F25W 1 $DEADLINE --env "$RWW" --env gait_frequency=2.5 --env stance_width=0.13 > /tmp/F25W.out 2>&1 < /dev/null &
setsid nohup bash -c "bash gpujob/accept2.sh A 2; bash gpujob/train.sh F2W 2 $DEADLINE --env \"$RWW\" --env gait_frequency=2.0 --env stance_width=0.13" > /tmp/F2W.out 2>&1 < /dev/null &
setsid nohup bash -c "bash gpujob/accept2.sh B 3; bash gpujob/train.sh F25toW 3 $DEADLINE --env \"$RWW\" --env gait_frequency=2.5 --env stance_width=0.13" > /tmp/F25toW.out 2>&1 < /dev/null &
bash gpujob/watch.sh $WATCH_S
