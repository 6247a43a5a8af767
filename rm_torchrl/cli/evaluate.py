"""``rmrl evaluate RUN_DIR``: the trainer's evaluation of a run's checkpoint (finished or interrupted)."""
from __future__ import annotations

import json


def add_arguments(p) -> None:
    p.add_argument("run_dir", help="a run directory (recipe.yaml and checkpoint.pt)")
    p.add_argument("--episodes", type=int, help="episodes (default: the recipe's eval.episodes)")
    p.add_argument("--seed", type=int, help="environment seed (default: the run's seed)")
    p.add_argument("--device", default="cpu", help="where the policy runs: cpu (default), cuda, cuda:N, auto")
    p.add_argument("--json", action="store_true", help="print JSON instead of a line of figures")
    p.add_argument("--video", metavar="FILE", help="also render episodes to FILE (.mp4 or .gif) with the RM state "
                                                 "drawn on each frame (MUJOCO_GL=egl without a display)")
    p.add_argument("--video-episodes", type=int, default=1, help="episodes in the video (default 1)")


def run(args) -> int:
    from rm_torchrl.errors import RMError
    from rm_torchrl.train.policy import load_policy

    if args.episodes is not None and args.episodes < 1:
        raise RMError(f"--episodes must be positive, got {args.episodes}")
    loaded = load_policy(args.run_dir, device=args.device)
    result = {"run": str(args.run_dir), "step": loaded.step, **loaded.evaluate(args.episodes, args.seed)}
    if args.video:
        result["video"] = str(loaded.video(args.video, episodes=args.video_episodes, seed=args.seed))
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{args.run_dir} at step {result['step']}: return {result['return_mean']:.1f} ± {result['return_std']:.1f} "
              f"({result['reward']} reward), score {result['score']:.1f}, success {result['success_rate']:.2f}, "
              f"events {result['events_mean']:.2f} over {result['episodes']} episodes"
              + (f"; video: {result['video']}" if args.video else ""))
    return 0
