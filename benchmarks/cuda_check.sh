#!/usr/bin/env bash
# The CUDA checks, as one script for a machine with an NVIDIA GPU:
# 1. the CUDA cases of the sparse-attention tests (CSR invariants, dense reference, no host reads);
# 2. both algorithms train on CUDA, save, and load on the CPU with the same greedy actions;
# 3. update and collection timings at default and paper size (float32 and bf16);
# 4. 15,000 env steps of the paper's Surviving map with the soft_hgrn defaults.
# Run: bash benchmarks/cuda_check.sh [LOG_DIR]   (logs go to LOG_DIR, default the current folder)
set -o pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
logs=${1:-.}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$logs/cuda_gpu.log"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)" | tee -a "$logs/cuda_gpu.log"
python3 -m pytest tests/test_hgrn.py -n 0 -p no:cacheprovider -q -rs -k cuda 2>&1 | tee "$logs/cuda_tests.log"
python3 - <<'PY' 2>&1 | tee "$logs/cuda_train.log"
import numpy as np
import torch as th
from sb3_hgrn import SACHGRN, SoftHGRN, make_graph_vec_env

for algorithm in (SoftHGRN, SACHGRN):
    env = make_graph_vec_env("surviving_v0", n_envs=2, seed=0, env_kwargs=dict(n_agents=20))
    model = algorithm("GraphPolicy", env, device="cuda", learning_starts=200, seed=0)
    model.learn(4_000)
    model.save("/tmp/cuda_model.zip")
    loaded = algorithm.load("/tmp/cuda_model.zip", device="cpu")
    obs = env.reset()
    on_gpu, _ = model.predict(obs, deterministic=True)
    on_cpu, _ = loaded.predict(obs, deterministic=True)
    print(algorithm.__name__, "trained on", model.device, "updates", model._n_updates,
          "same actions on the CPU:", bool(np.array_equal(on_gpu, on_cpu)))
PY
python3 benchmarks/throughput.py --device cuda --sizes default paper paper-bf16 --batch-sizes 32 128 \
    --updates 10 --buffer-rows 1000 2>&1 | tee "$logs/cuda_throughput.log"
python3 benchmarks/surviving_paper_map.py --device cuda --seeds 0 2>&1 | tee "$logs/cuda_paper_map.log"
