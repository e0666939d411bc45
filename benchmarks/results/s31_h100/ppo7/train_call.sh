# session 31 training call (the seventh run): dr_legs_joystick PPO from scratch with a tracking kernel that pays
# tracking (sigma 0.1, weight 1.5), the gait clock at 1.5 Hz (feet_phase 1.0), lin_vel_z, ang_vel_xy, discounting 0.98;
# resumes from /tmp/rl_7 when there; the walking test (128 x 10 s, seed 1) on every checkpoint from $2 steps.
source gpujob/env.sh
T=${1:-480}; FROM=${2:-20000000}; shift; shift
mkdir -p /tmp/rl_7
timeout $T python3 benchmarks/rl_train.py dr_legs_joystick --backend warp --num-envs 16384 --set batch_size=512 \
  --steps 100000000 --evals 25 --set run_evals=False --train-returns 1310720 --walk-test 128 --walk-test-from $FROM \
  --env gait_frequency=1.5 --env command_lin_x=0.6 --env tracking_sigma=0.1 \
  --env "reward_weights={'tracking_lin_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}" \
  --set entropy_cost=0.005 --set discounting=0.98 \
  "$@" --out /tmp/rl_7 > /tmp/train.log 2>&1
echo "train rc $?"
grep "walking test" /tmp/train.log
cp /tmp/rl_7/walk_tests.json /tmp/rl_7/train_curve.json $OUT/ 2>/dev/null
grep -v "^W1\|^I1" /tmp/train.log | tr '\r' '\n' | grep -v "^\s*$" > $OUT/train.log
cd /tmp/rl_7 && tar -czf $OUT/ckpts.tgz checkpoints $(ls walk_tests.json train_curve.json curve.json report.json 2>/dev/null)
python3 -c "
import json
c=json.load(open('/tmp/rl_7/train_curve.json'))
for e in c[-8:]: print(e['step'], round(e['reward'],3), round(e['length'],1), round(e['env_steps_per_s']), {k: round(v,2) for k,v in e['episode'].items() if k in ('tracking_lin_vel','failed','feet_phase','lin_vel_z','ang_vel_xy')})
"
