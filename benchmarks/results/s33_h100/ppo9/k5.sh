# session 33 (planned) training: continue run NAME (A or B of session 32's eighth run, from gpujob/ckNAME.tgz at
# 72.4 M) on the GPUs GPUS (e.g. "0,1": brax pmaps over them; 16384 environments and batch 512 per GPU), with the
# seventh run's settings plus "$@" (B: --env "reward_weights=...'alive': 1.0"), until the epoch DEADLINE; the
# walking test on every checkpoint with 256 episodes (the count; it costs the same as 128 on the GPU).
# usage: bash gpujob/k5.sh NAME GPUS DEADLINE [extra rl_train args]
source gpujob/env.sh
NAME=$1; GPUS=$2; DEADLINE=$3; shift 3
N=$(echo $GPUS | tr ',' '\n' | wc -l)
D=/tmp/rl_$NAME; mkdir -p $D
[ -d $D/checkpoints ] || tar -xzf gpujob/ck${CK:-$NAME}.tgz -C $D  # CK: another run's checkpoint (A1 continues A)
export CUDA_VISIBLE_DEVICES=$GPUS WARP_CACHE_PATH=/tmp/wc_$NAME JAX_COMPILATION_CACHE_DIR=/tmp/jc_$NAME
T=$(( DEADLINE - $(date +%s) ))
echo "$NAME on GPUs $GPUS ($N) for $T s: $*" > $D/cmd.txt
timeout $T python3 benchmarks/rl_train.py dr_legs_joystick --backend warp --num-envs $((16384 * N)) \
  --set batch_size=$((512 * N)) --steps 300000000 --evals $((75 / N)) --set run_evals=False --train-returns $((1310720 * N)) \
  --walk-test 256 --walk-test-from 70000000 \
  --env gait_frequency=1.5 --env command_lin_x=0.6 --env tracking_sigma=0.1 \
  --set entropy_cost=0.005 --set discounting=0.98 \
  "$@" --out $D > $D/train.log 2>&1
echo "train rc $?" >> $D/cmd.txt
