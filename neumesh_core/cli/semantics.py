"""`neumesh semantics`: distill semantic codes into a field file (saved beside it as an edit)."""
from __future__ import annotations

import sys
import time

from .common import Progress


def add_commands(sub) -> None:
    p = sub.add_parser(
        "semantics", help="distill per-vertex semantic codes from 2D image features (for one-click selection)",
        description="Extract 2D features from the training images, fit the field's semantic codes and "
                    "decoder to them (geometry and appearance stay frozen) and save the result beside the "
                    "field as <name>.edit-NNN.neumesh (or --out). Ctrl-C cancels without writing.")
    p.add_argument("--field", required=True, help="trained field file (.neumesh)")
    p.add_argument("--data", required=True, help="the dataset the field was trained on")
    p.add_argument("--out", help="output field file (default: the next <name>.edit-NNN.neumesh beside --field)")
    p.add_argument("--downscale", type=float, default=1, help="image downscale factor (default 1)")
    p.add_argument("--background", choices=["white", "black"], default="white",
                   help="background colour that RGBA images are composited on")
    p.add_argument("--extractor", default=None,
                   help="2D features: colour-texture (default, weight-free), dino-vits8, dino-vits16, dino-vitb8, "
                        "dino-vitb16, dinov2-small, dinov2-base (local weights: see --weights)")
    p.add_argument("--weights", default=None,
                   help="DINO weights file or folder (default: $NEUMESH_WEIGHTS/<model>.safetensors or the "
                        "Hugging Face cache); nothing is downloaded")
    p.add_argument("--sem-dim", type=int, default=8, help="semantic code per vertex (default 8)")
    p.add_argument("--pca", type=int, default=16,
                   help="PCA of the 2D features to this width (0 = keep all; default 16)")
    p.add_argument("--steps", type=int, default=1500, help="optimisation steps (default 1500)")
    p.add_argument("--rays-per-view", type=int, default=4096, help="rays drawn per training view (default 4096)")
    p.add_argument("--max-views", type=int, default=None, help="use at most this many training views")
    p.add_argument("--threads", type=int, default=None, help="CPU threads for torch (default: all)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.set_defaults(func=cmd_semantics)


def cmd_semantics(args) -> int:
    import neumesh_core as nm
    from ..edit import save_edited

    from ..semantics.distill import DistillConfig, distill_semantics, semantics_record
    from ..semantics.extractors import make_extractor

    try:
        cfg = DistillConfig(sem_dim=args.sem_dim, pca_dim=args.pca or None, steps=args.steps,
                            rays_per_view=args.rays_per_view, max_views=args.max_views, threads=args.threads,
                            seed=args.seed)
    except ValueError as exc:
        raise nm.NeuMeshError(f"semantics options: {exc}") from exc
    field = nm.load_field(args.field)
    scene = nm.load_scene(args.data, downscale=args.downscale, background=args.background)
    try:
        extractor = make_extractor(args.extractor, weights=args.weights)
    except ValueError as exc:
        raise nm.NeuMeshError(f"semantics options: {exc}") from exc
    t0 = time.perf_counter()
    progress = Progress()
    try:
        res = distill_semantics(field, scene, extractor, cfg, progress=progress.semantics)
    except KeyboardInterrupt:
        progress.say("interrupted; nothing written")
        return 130
    progress.end()
    if res.cancelled:
        print("cancelled; nothing written", file=sys.stderr)
        return 1
    record = semantics_record(field, res)
    out = save_edited(field, args.field, record, out_path=args.out)
    print(f"semantics: {res.steps_done} steps, loss {res.final_loss:.4f}, {res.bank_rays} rays, "
          f"{res.feature_channels} feature channels ({extractor.name}); "
          f"features {res.timings.get('features_s', 0):.1f}s, "
          f"rays {res.timings.get('rays_s', 0):.1f}s, training {res.timings.get('train_s', 0):.1f}s, "
          f"total {time.perf_counter() - t0:.1f}s; wrote {out}")
    return 0
