#!/bin/bash
# The CUDA checks and timings: run from the repository root on a
# machine with a CUDA GPU, the package installed (pip install -e .[dev]; on a machine that reaches no
# registry but has torch, scikit-learn, scikit-image and rich: carry the wheels of tyro, docstring-parser,
# shtab and typeguard, install them, then pip install --no-deps --no-build-isolation -e .).
# Writes logs to ${OUT:-gpu_check}/.
# CUDA against CPU (tests/test_cuda.py), the cpu preset on the four built-in scenes on the GPU,
# foot with four times the epochs, and the paper preset's step rate (100 + 100 steps).
out=${OUT:-gpu_check}; mkdir -p "$out"
export PYTHONUNBUFFERED=1
nvidia-smi -L; python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name())"
python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py 2>&1 | tee "$out/pytest_cuda.log" | tail -3
summary() {  # the newest run under $1: psnr3d, ssim3d, K, steps and the times per stage
  python3 -c "import json,glob,sys; m=json.load(open(sorted(glob.glob(sys.argv[1]+'/*/metrics.json'))[-1])); print(sys.argv[1], {k: round(m[k], 3) if isinstance(m[k], float) else m[k] for k in ('psnr3d','ssim3d','num_materials','steps','wall_time_s','train_time_s','correction_time_s','eval_time_s','prior_time_s')})" "$1"
}
for s in foot jaw chest abdomen; do
  kneas-train k-neas --scene $s --preset cpu --device cuda --output-dir "$out/runs" > "$out/$s.log" 2>&1; summary "$out/runs/$s/k-neas"
done
kneas-train k-neas --scene foot --preset cpu --device cuda --trainer.epochs 160 --output-dir "$out/runs160" > "$out/foot160.log" 2>&1
summary "$out/runs160/foot/k-neas"
kneas-train k-neas --scene foot --preset paper --device cuda --trainer.prior-epochs 2 --trainer.epochs 2 --output-dir "$out/paper" > "$out/paper.log" 2>&1
grep "steps/s" "$out/paper.log"; summary "$out/paper/foot/k-neas"
