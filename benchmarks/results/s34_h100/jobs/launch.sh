# session 34, the call after the install on an nvidia-h100-x4: copy the tree to /tmp/repo; the tenth training run
# (variants from scratch: Y, YF on GPUs 0-1, YFS on GPU 3 after m7.sh) and issue 17's acceptance run (p1.sh, GPU 2), all detached,
# training until now + $1 s; then watch for $2 s.
TRAIN_S=$1; WATCH_S=$2
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + TRAIN_S )); echo $DEADLINE > /tmp/deadline
# the seventh run's weights, and the yaw-rate term tripled (0.5 -> 1.5)
RWY="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}"
setsid nohup bash gpujob/train.sh Y 0 $DEADLINE --env "$RWY" > /tmp/Y.out 2>&1 < /dev/null &
setsid nohup bash gpujob/train.sh YF 1 $DEADLINE --env "$RWY" --env gait_frequency=2.0 > /tmp/YF.out 2>&1 < /dev/null &
setsid nohup bash gpujob/p1.sh > /tmp/p1.out 2>&1 < /dev/null &
setsid nohup bash -c "bash gpujob/m7.sh > /tmp/m7.out 2>&1; bash gpujob/train.sh YFS 3 $DEADLINE --env \"$RWY\" --env gait_frequency=2.0 --env tracking_sigma=0.05" > /tmp/YFS.out 2>&1 < /dev/null &
bash gpujob/mon.sh $WATCH_S
