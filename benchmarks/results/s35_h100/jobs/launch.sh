# GPUs 0-2: three dr_legs_joystick variants from scratch that test the lateral-sway reading (docs/envs.md, "The
# lateral sway"); GPU 3: issue 17's acceptance run (accept.sh, about 17 min). Training until now + $1 s;
# then watch (and collect) for $2 s.
TRAIN_S=$1; WATCH_S=$2
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + TRAIN_S )); echo $DEADLINE > /tmp/deadline
RWW="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05, 'feet_width': 0.5}"
RWY="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}"
setsid nohup bash gpujob/train.sh F25 0 $DEADLINE --env "$RWY" --env gait_frequency=2.5 > /tmp/F25.out 2>&1 < /dev/null &
setsid nohup bash gpujob/train.sh F2W 1 $DEADLINE --env "$RWW" --env gait_frequency=2.0 --env stance_width=0.13 > /tmp/F2W.out 2>&1 < /dev/null &
setsid nohup bash gpujob/train.sh F25W 2 $DEADLINE --env "$RWW" --env gait_frequency=2.5 --env stance_width=0.13 > /tmp/F25W.out 2>&1 < /dev/null &
setsid nohup bash gpujob/accept.sh > /tmp/accept.out 2>&1 < /dev/null &
bash gpujob/watch.sh $WATCH_S
