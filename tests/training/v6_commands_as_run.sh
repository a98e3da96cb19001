# The commands that made repnet-h36m-v6's generator and critic (v7 = v6's generator and critic with
# the pose density): the record tests/training/test_presets.py holds the preset to, flag for flag.
# As run on the 2-core CPU machine; paths as they were.
R=~/.cache/repnet/runs
# stretch 1 (session 2, v3's run): 60,000 steps
python -m repnet.train.train --out-dir $R/long512x3 --inputs gt+sh --batch-size 256 --lr 1e-3 \
  --schedule cosine --lr-decay 0.01 --iterations 60000 --warm-start-steps 60000 --bone-weight 3 --width 512 \
  --val-every 1000 --val-size 4000 --log-every 50 --checkpoint-every 2000 --checkpoint-minutes 10 \
  --max-minutes 150 --threads 2 --resume auto
# stretch 2 (session 2, ~/.cache/repnet/long512x3b.sh): the same on a 120,000-step cosine from step 60,000
mkdir -p $R/long512x3b && cp $R/long512x3/last.pt $R/long512x3/history.jsonl $R/long512x3b/
python -m repnet.train.train --out-dir $R/long512x3b --inputs gt+sh --batch-size 256 --lr 1e-3 \
  --schedule cosine --lr-decay 0.01 --iterations 120000 --warm-start-steps 120000 --bone-weight 3 --width 512 \
  --val-every 1000 --val-size 4000 --log-every 50 --checkpoint-every 2000 --checkpoint-minutes 10 \
  --max-minutes 200 --threads 2 --resume auto
# stretch 3 (session 3, ~/.cache/repnet/session3.sh): 16 min as one arm of round 1 (one thread),
# then, having won, the rest of its schedule on two threads (the same command with --threads 2)
python -m repnet.train.train --out-dir $R/s3_mirror --init-from $R/long512x3b/best.pt --inputs gt+sh \
  --batch-size 256 --lr 3e-4 --schedule cosine --lr-decay 0.0333 --iterations 100000 \
  --warm-start-steps 100000 --bone-weight 3 --width 512 --val-every 1000 --val-size 4000 --log-every 50 \
  --checkpoint-every 2000 --checkpoint-minutes 5 --resume auto --mirror-prob 0.5 --threads 1 --max-minutes 16
python -m repnet.train.train ... --mirror-prob 0.5 --threads 2 --max-minutes 95
# v2's critic (trained against corrupted real poses, generator frozen), session 1:
python -m repnet.train.train --out-dir $R/long_critic_corrupted --inputs gt+sh --batch-size 256 \
  --lr 1e-4 --schedule constant --iterations 23000 --critic-only true --critic-steps 1 --critic-fakes corrupted \
  --val-every 1000 --val-size 4000 --log-every 50 --checkpoint-every 1000 --threads 2 --resume $R/long/best.pt
python -m repnet.train.validate --checkpoint $R/s3_mirror/best.pt --mirror-average --threads 2
python -m repnet.train.export --checkpoint $R/s3_mirror/best.pt --critic-checkpoint $R/long_critic_corrupted/last.pt \
  --mirror-average true --output runs/model_v4/repnet-h36m.onnx --model-id repnet-h36m-v4
python -m repnet.train.evaluate --model runs/model_v4/repnet-h36m.onnx --inputs gt --out-dir runs/eval_v4 --threads 2
python -m repnet.train.export ... --evaluation runs/eval_v4/evaluation.json   # the same export, figures embedded
cp runs/model_v4/repnet-h36m.onnx service/models/repnet-h36m.onnx
# session 4: the checkpoints above were gone; v4's generator read back from the shipped file
cp service/models/repnet-h36m.onnx ~/.cache/repnet/repnet-h36m-v4.onnx   # (git show f1ef147:service/models/repnet-h36m.onnx)
python -m repnet.train.validate --checkpoint ~/.cache/repnet/repnet-h36m-v4.onnx --mirror-average --threads 2
# stretch 4 (~/.cache/repnet/session4.sh, round 1's power-3 arm): 30,000 steps, one thread beside the power-2 arm
python -m repnet.train.train --out-dir $R/s4_p3 --init-from ~/.cache/repnet/repnet-h36m-v4.onnx --inputs gt+sh \
  --batch-size 256 --lr 1e-4 --schedule cosine --lr-decay 0.1 --iterations 30000 --warm-start-steps 30000 \
  --bone-weight 3 --width 512 --val-every 1000 --val-size 4000 --log-every 50 --checkpoint-every 2000 \
  --checkpoint-minutes 5 --resume auto --mirror-prob 0.5 --synthetic-noise-px 20 --threads 1 --max-minutes 32 \
  --synthetic-noise-power 3
# stretch 5 (~/.cache/repnet/session4b.sh, round 2's power-4 arm = v5): 42 min, one thread beside the power-3 arm
python -m repnet.train.train --out-dir $R/s4b_p4 --init-from $R/s4_p3/last.pt --inputs gt+sh --batch-size 256 \
  --lr 5e-5 --schedule cosine --lr-decay 0.02 --iterations 45000 --warm-start-steps 45000 --bone-weight 3 \
  --width 512 --val-every 1000 --val-size 4000 --log-every 50 --checkpoint-every 2000 --checkpoint-minutes 5 \
  --resume auto --mirror-prob 0.5 --synthetic-noise-px 20 --threads 1 --max-minutes 42 --synthetic-noise-power 4
python -m repnet.train.validate --checkpoint $R/s4b_p4/last.pt --mirror-average --noise-px 40 --threads 2
# v4's critic (v2's) comes from the shipped v4 file
python -m repnet.train.export --checkpoint $R/s4b_p4/last.pt --critic-checkpoint ~/.cache/repnet/repnet-h36m-v4.onnx \
  --mirror-average true --output runs/model_v5/repnet-h36m.onnx --model-id repnet-h36m-v5
python -m repnet.train.evaluate --model runs/model_v5/repnet-h36m.onnx --inputs gt --out-dir runs/eval_v5 --threads 2
python -m repnet.train.export ... --evaluation runs/eval_v5/evaluation.json   # the same export, figures embedded
cp runs/model_v5/repnet-h36m.onnx service/models/repnet-h36m.onnx
# session 5 (~/.cache/repnet/session5b.sh, round 1's arm B): stretch 6, 45,000 steps, one thread
python -m repnet.train.train --out-dir $R/s5_mask25 --init-from ~/.cache/repnet/repnet-h36m-v5.onnx --inputs gt+sh \
  --batch-size 256 --lr 5e-5 --schedule cosine --lr-decay 0.02 --iterations 45000 --warm-start-steps 45000 \
  --bone-weight 3 --width 512 --val-every 1000 --val-size 4000 --log-every 50 --checkpoint-every 2000 \
  --checkpoint-minutes 5 --resume auto --mirror-prob 0.5 --synthetic-noise-px 20 --synthetic-noise-power 4 \
  --mask-prob 0.25 --threads 1 --max-minutes 100
# stretch 7 (~/.cache/repnet/session5r2.sh, round 2's arm D = v6): 60,000 steps, one thread
python -m repnet.train.train --out-dir $R/s5_r2_limbs --init-from $R/s5_mask25/last.pt --inputs gt+sh \
  --batch-size 256 --lr 1e-4 --schedule cosine --lr-decay 0.01 --iterations 60000 --warm-start-steps 60000 \
  --bone-weight 3 --width 512 --val-every 1000 --val-size 4000 --log-every 50 --checkpoint-every 2000 \
  --checkpoint-minutes 5 --resume auto --mirror-prob 0.5 --synthetic-noise-px 20 --synthetic-noise-power 4 \
  --mask-prob 0.25 --threads 1 --max-minutes 60 --limb-turn-deg 10 --limb-turn-prob 0.5
python -m repnet.train.validate --checkpoint $R/s5_r2_limbs/last.pt --mirror-average --noise-px 40 --hidden-joints 1 2 3 --threads 1
# the critic (v2's) comes from the shipped v5 file
python -m repnet.train.export --checkpoint $R/s5_r2_limbs/last.pt --critic-checkpoint ~/.cache/repnet/repnet-h36m-v5.onnx \
  --mirror-average true --output runs/model_v6/repnet-h36m.onnx --model-id repnet-h36m-v6
python -m repnet.train.evaluate --model runs/model_v6/repnet-h36m.onnx --inputs gt --out-dir runs/eval_v6 --threads 2
python -m repnet.train.export ... --evaluation runs/eval_v6/evaluation.json   # the same export, figures embedded
cp runs/model_v6/repnet-h36m.onnx service/models/repnet-h36m.onnx
