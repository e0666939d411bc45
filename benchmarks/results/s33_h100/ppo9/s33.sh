# session 33 (planned), the call after the install on an nvidia-h100-x4: copy the tree to /tmp/repo, continue A on
# GPUs 0,1 and B on GPU 2 (k5.sh), hunt blow-ups on GPU 3 (rl_blowup_hunt.py), detached, until now + $1 s; watch for $2 s (then gpujob/mon.sh, gpujob/col.sh)
TRAIN_S=$1; WATCH_S=$2
rm -rf /tmp/repo && mkdir -p /tmp/repo && cp -r . /tmp/repo/ && cd /tmp/repo
DEADLINE=$(( $(date +%s) + TRAIN_S )); echo $DEADLINE > /tmp/deadline
RW7="reward_weights={'tracking_lin_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05}"
RWA="reward_weights={'tracking_lin_vel': 1.5, 'feet_phase': 1.0, 'lin_vel_z': -2.0, 'ang_vel_xy': -0.05, 'alive': 1.0}"
setsid nohup bash gpujob/k5.sh A 0,1 $DEADLINE --env "$RW7" > /tmp/A.out 2>&1 < /dev/null &
sleep 20
setsid nohup bash gpujob/k5.sh B 2 $DEADLINE --env "$RWA" > /tmp/B.out 2>&1 < /dev/null &
# GPU 3: the memory/speed job m6.sh, then catch finite blow-ups of A's 72.4 M policy (about 20 expected in 13 M env steps: one per ~0.6 M) and replay one on the GPU
mkdir -p /tmp/hunt
cat > /tmp/hunt.sh <<EOD
cd /tmp/repo; bash gpujob/m6.sh > /tmp/m6.out 2>&1  # first the shared per-row vectors' speed and memory (~4 min)
cd /tmp/repo; source gpujob/env.sh; export CUDA_VISIBLE_DEVICES=3 WARP_CACHE_PATH=/tmp/wc_H JAX_COMPILATION_CACHE_DIR=/tmp/jc_H
timeout 500 python3 benchmarks/rl_blowup_hunt.py gpujob/ckA_dir --envs 16384 --chunks 16 --chunk-steps 50 \
  --env gait_frequency=1.5 --env command_lin_x=0.6 --env tracking_sigma=0.1 --env "$RW7" --out /tmp/hunt
timeout 120 python3 benchmarks/rl_blowup_hunt.py --replay /tmp/hunt/case_000.pkl > /tmp/hunt/replay_000_gpu.txt 2>&1
CK=A bash gpujob/k5.sh A1 3 $DEADLINE --env "$RW7"  # then A alone on one GPU: pmap's gain per step
EOD
mkdir -p gpujob/ckA_dir && tar -xzf gpujob/ckA.tgz -C gpujob/ckA_dir
setsid nohup bash /tmp/hunt.sh > /tmp/hunt.out 2>&1 < /dev/null &
bash gpujob/mon.sh $WATCH_S
