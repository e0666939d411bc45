# one PPO run of dr_legs_joystick from scratch on GPU $2 (16384 environments, batch 512 x 32), the seventh run's
# settings plus "$@", until the epoch DEADLINE; checkpoints every 4 M steps; the walking test (128 episodes, seed 1)
# on every checkpoint from 36 M steps. usage: bash gpujob/train.sh NAME GPU DEADLINE [extra rl_train args]
cd /tmp/repo; export PYTHONPATH=/tmp/site:/tmp/repo PYTHONUNBUFFERED=1
NAME=$1; GPU=$2; DEADLINE=$3; shift 3
D=/tmp/rl_$NAME; mkdir -p $D
export CUDA_VISIBLE_DEVICES=$GPU WARP_CACHE_PATH=/tmp/wc_$NAME JAX_COMPILATION_CACHE_DIR=/tmp/jc_$NAME
T=$(( DEADLINE - $(date +%s) ))
echo "$NAME on GPU $GPU for $T s: $*" > $D/cmd.txt
timeout $T python3 benchmarks/rl_train.py dr_legs_joystick --backend warp --num-envs 16384 --set batch_size=512 \
  --steps 300000000 --evals 75 --set run_evals=False --train-returns 1310720 \
  --walk-test 128 --walk-test-from 36000000 \
  --env gait_frequency=1.5 --env command_lin_x=0.6 --env tracking_sigma=0.1 \
  --set entropy_cost=0.005 --set discounting=0.98 \
  "$@" --out $D > $D/train.log 2>&1
echo "train rc $?" >> $D/cmd.txt
