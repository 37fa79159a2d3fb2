"""The one entry point: `avatar-motor <command>`. Argument parsing only; the work lives in the rooms."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _train(a) -> int:
    from .train.trainer import TrainConfig, Trainer

    d = json.loads(Path(a.config).read_text()) if a.config else {}
    for k in ("steps", "out", "batch", "seed", "threads"):
        if getattr(a, k) is not None:
            d[k] = getattr(a, k)
    cfg = TrainConfig.from_dict(d)
    tr = Trainer(cfg)
    print(f"training {cfg.name}: {sum(p.numel() for p in tr.net.parameters()) / 1e6:.2f} M parameters, "
          f"{len(tr.ds)} windows from {tr.ds.frames_total} frames, batch {cfg.batch}, to step {cfg.steps}, out {cfg.out}", flush=True)
    tr.run()
    print(f"done at step {tr.step}; EMA checkpoint in {Path(cfg.out) / 'checkpoint'}", flush=True)
    return 0


def _data_import(a) -> int:
    from .data.cache import format_summary, import_motion
    from .data.retarget import load_mapping_file

    mapping = load_mapping_file(a.mapping) if a.mapping else None
    _, summary = import_motion(a.path, name=a.name, cache_dir=a.cache_dir, workers=a.workers, mapping=mapping, unit=a.unit)
    print(format_summary(summary))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="avatar-motor", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    t = sub.add_parser("train", help="train a base motor model (resumes from --out if a state is there)")
    t.add_argument("--config", help="JSON training config (see configs/base.json); defaults work without one")
    t.add_argument("--steps", type=int)
    t.add_argument("--out")
    t.add_argument("--batch", type=int)
    t.add_argument("--seed", type=int)
    t.add_argument("--threads", type=int)
    t.set_defaults(func=_train)

    d = sub.add_parser("data", help="import and inspect motion").add_subparsers(dest="dcmd", required=True)
    i = d.add_parser("import", help="convert BVH (folder, file, .tar.xz or .zip) into the motion cache")
    i.add_argument("path")
    i.add_argument("--name", help="dataset name (default: from the path)")
    i.add_argument("--cache-dir", help="default: $AVATAR_MOTOR_CACHE or ~/.cache/avatar-motor, /motion")
    i.add_argument("--workers", type=int)
    i.add_argument("--mapping", help="JSON file {canonical joint: source joint} for unknown skeletons")
    i.add_argument("--unit", choices=["m", "dm", "cm", "mm", "in", "ft"], help="override unit detection")
    i.set_defaults(func=_data_import)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, KeyError) as e:
        print(f"avatar-motor: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
