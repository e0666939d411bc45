# session 32 training (the eighth run, a sweep): one PPO run per GPU, each resumed from the seventh run's 29.5 M
# checkpoint with the seventh run's settings plus "$@" (reward or command changes); stops at the epoch DEADLINE.
# usage: bash gpujob/k4.sh NAME GPU DEADLINE [extra rl_train args]
source gpujob/env.sh
NAME=$1; GPU=$2; DEADLINE=$3; shift 3
D=/tmp/rl_$NAME; mkdir -p $D
[ -d $D/checkpoints ] || tar -xzf gpujob/ckpts7.tgz -C $D
export CUDA_VISIBLE_DEVICES=$GPU WARP_CACHE_PATH=/tmp/wc_$NAME JAX_COMPILATION_CACHE_DIR=/tmp/jc_$NAME
T=$(( DEADLINE - $(date +%s) ))
echo "$NAME on GPU $GPU for $T s: $*" > $D/cmd.txt
timeout $T python3 benchmarks/rl_train.py dr_legs_joystick --backend warp --num-envs 16384 --set batch_size=512 \
  --steps 100000000 --evals 25 --set run_evals=False --train-returns 1310720 --walk-test 128 --walk-test-from 30000000 \
  --env gait_frequency=1.5 --env command_lin_x=0.6 --env tracking_sigma=0.1 \
  --set entropy_cost=0.005 --set discounting=0.98 \
  "$@" --out $D > $D/train.log 2>&1
echo "train rc $?" >> $D/cmd.txt
