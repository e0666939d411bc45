# Session 37's job (planned in session 36). Training: session 35's train.sh (benchmarks/results/s35_h100/jobs/next/
# train.sh, unchanged), at a FIXED learning rate (docs/envs.md, "The eleventh run": brax's ADAPTIVE_KL held every
# run since session 27 at its 1e-5 floor):
#   GPU 0, L3: F25 resumed from benchmarks/results/s36_h100/F25 (123.5 M), learning rate 3e-4 (the config's)
#   GPU 1, S3: F25W's settings (2.5 Hz + feet_width) from scratch, 3e-4: compare with the tenth run at equal steps
#   GPU 2: accept3.sh A (issue 17: the four-bar, ladder8, animatronic with the peers), then L1: F25 resumed at 1e-4
#   GPU 3: accept3.sh B (issue 17: the robots and ladder32 with the peers, every size), then W3: F25toW resumed at 3e-4
# Training until now + $1 s; then watch (and collect) for $2 s.
TRAIN_S=$1; WATCH_S=$2
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + TRAIN_S )); echo $DEADLINE > /tmp/deadline
S=benchmarks/results/s36_h100; T=benchmarks/results/s35_h100/jobs/next/train.sh
for n in L3 S3 L1 W3; do rm -rf /tmp/rl_$n; mkdir -p /tmp/rl_$n; done
for n in L3 L1; do cp -r $S/F25/checkpoints $S/F25/*.json /tmp/rl_$n/; done
cp -r $S/F25toW/checkpoints $S/F25toW/*.json /tmp/rl_W3/
RWW="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05, 'feet_width': 0.5}"
RWY="reward_weights={'tracking_lin_vel': 1.5, 'tracking_ang_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}"
FIX="--set learning_rate_schedule=None"
setsid nohup bash $T L3 0 $DEADLINE --env "$RWY" --env gait_frequency=2.5 $FIX > /tmp/L3.out 2>&1 < /dev/null &
setsid nohup bash $T S3 1 $DEADLINE --env "$RWW" --env gait_frequency=2.5 --env stance_width=0.13 $FIX > /tmp/S3.out 2>&1 < /dev/null &
setsid nohup bash -c "bash gpujob/accept3.sh A 2; bash $T L1 2 $DEADLINE --env \"$RWY\" --env gait_frequency=2.5 $FIX --set learning_rate=1e-4" > /tmp/L1.out 2>&1 < /dev/null &
setsid nohup bash -c "bash gpujob/accept3.sh B 3; bash $T W3 3 $DEADLINE --env \"$RWW\" --env gait_frequency=2.5 --env stance_width=0.13 $FIX" > /tmp/W3.out 2>&1 < /dev/null &
bash gpujob/watch.sh $WATCH_S
