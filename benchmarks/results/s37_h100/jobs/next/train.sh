# one PPO run of dr_legs_joystick on GPU $2 at the task's config (kamino/envs/configs.py: L3's recipe, 16384
# environments, batch 512 x 32, a fixed 3e-4), resuming the checkpoints in /tmp/rl_NAME with the run's env.json, until
# the epoch DEADLINE; the walking test (128 episodes, seed 1) from 36 M steps, at most one every 8 M steps.
# usage: bash gpujob/train.sh NAME GPU DEADLINE [extra rl_train args]
cd /tmp/repo; export PYTHONPATH=/tmp/site:/tmp/repo PYTHONUNBUFFERED=1
NAME=$1; GPU=$2; DEADLINE=$3; shift 3
D=/tmp/rl_$NAME; mkdir -p $D
export CUDA_VISIBLE_DEVICES=$GPU WARP_CACHE_PATH=/tmp/wc_$NAME JAX_COMPILATION_CACHE_DIR=/tmp/jc_$NAME
T=$(( DEADLINE - $(date +%s) ))
echo "$NAME on GPU $GPU for $T s: $*" >> $D/cmd.txt
timeout $T python3 benchmarks/rl_train.py dr_legs_joystick --backend warp --evals 75 --set run_evals=False \
  --train-returns 1310720 --walk-test 128 --walk-test-from 36000000 --walk-test-every 8000000 "$@" --out $D \
  > $D/train.log 2>&1
echo "train rc $?" >> $D/cmd.txt
