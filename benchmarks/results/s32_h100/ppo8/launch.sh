# session 32, call 6 (after the install): copy the tree to /tmp/repo (later calls re-sync the checkout), start the
# sweep (k4.sh: A, B, C on GPUs 1-3 now; D on GPU 0 after the memory/speed job m5.sh), all detached, ending at
# now + $1 s; then watch for $2 s.
TRAIN_S=$1; WATCH_S=$2
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + TRAIN_S )); echo $DEADLINE > /tmp/deadline
RW7="reward_weights={'tracking_lin_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}"
RWA="reward_weights={'tracking_lin_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05, 'alive': 1.0}"
setsid nohup bash gpujob/k4.sh A 1 $DEADLINE --env "$RW7" > /tmp/A.out 2>&1 < /dev/null &
sleep 20
setsid nohup bash gpujob/k4.sh B 2 $DEADLINE --env "$RWA" > /tmp/B.out 2>&1 < /dev/null &
sleep 20
setsid nohup bash gpujob/k4.sh C 3 $DEADLINE --env "$RWA" --env command_lin_y=0.15 --env command_yaw=0.4 > /tmp/C.out 2>&1 < /dev/null &
cat > /tmp/d.sh <<EOD
cd /tmp/repo
bash gpujob/m5.sh > /tmp/m5.out 2>&1
bash gpujob/k4.sh D 0 $DEADLINE --env "$RWA" --set entropy_cost=0.001
EOD
setsid nohup bash /tmp/d.sh > /tmp/D.out 2>&1 < /dev/null &
bash gpujob/mon.sh $WATCH_S
