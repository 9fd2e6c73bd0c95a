"""``dars poses PHOTOS_DIR --out SCENE_DIR``: camera poses from a folder of photos (pycolmap), an upright scene."""

from __future__ import annotations

import argparse

from ._common import log as _log_line, print_json

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
                 "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "FOV", "THIN_PRISM_FISHEYE")
"""As :data:`toolkit.poses.CAMERA_MODELS` (repeated so ``--help`` imports nothing heavy; a test holds them equal)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    from types import SimpleNamespace

    # PosesConfig's defaults (toolkit.poses imports numpy; tests/test_poses.py holds these equal)
    d = SimpleNamespace(matcher="auto", exhaustive_limit=150, max_size=1600, camera_model="SIMPLE_RADIAL", overlap=10,
                        min_registered=0.8, num_threads=-1, seed=0)
    q = sub.add_parser(
        "poses", help="camera poses from a folder of photos (pycolmap: SIFT, matching, mapping, undistortion)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Camera poses from a folder of photos with COLMAP (pycolmap, CPU): SIFT features, matching, "
                    "incremental mapping, undistortion to pinhole; the scene is rotated so that world up is +z.\n"
                    "SCENE_DIR gets transforms.json (dars, nerfstudio and instant-ngp read it), images/ (undistorted), "
                    "sparse_pc.ply, sparse/0 (COLMAP model), colmap/ (database for --resume) and dars_manifest.json.\n"
                    "Nothing is downloaded and nothing is written into PHOTOS_DIR; a non-empty SCENE_DIR that dars "
                    "did not make is refused.")
    q.add_argument("photos", metavar="PHOTOS_DIR", help="folder of photos (JPEG, PNG, TIFF, BMP; subfolders included)")
    q.add_argument("--out", required=True, metavar="SCENE_DIR", help="output scene folder (new, empty, or made by dars poses)")
    q.add_argument("--matcher", choices=["auto", "exhaustive", "sequential"], default=d.matcher,
                   help=f"pairs to match: all (exhaustive), neighbours in name order (sequential), or auto: exhaustive "
                        f"up to {d.exhaustive_limit} photos (default: {d.matcher})")
    q.add_argument("--max-size", type=int, default=d.max_size, metavar="PX",
                   help=f"longest image side for features and for the written images; 0 = full size (default: {d.max_size})")
    q.add_argument("--camera-model", choices=CAMERA_MODELS, default=d.camera_model, metavar="MODEL",
                   help=f"COLMAP camera model of the photos: {', '.join(CAMERA_MODELS)} (default: {d.camera_model}); "
                        "OPENCV for strong distortion (wide phone lenses), *_FISHEYE for fisheye lenses")
    q.add_argument("--single-camera", action=argparse.BooleanOptionalAction, default=None,
                   help="one camera for all photos / one per photo (default: one per photo size and EXIF camera, "
                        "i.e. one for a folder from one camera)")
    q.add_argument("--overlap", type=int, default=d.overlap,
                   help=f"sequential matching: neighbours matched per photo (default: {d.overlap})")
    q.add_argument("--vocab-tree", metavar="FILE",
                   help="sequential matching: loop closure with this COLMAP vocabulary-tree file (the FAISS format of "
                        "COLMAP >= 3.11, e.g. vocab_tree_faiss_flickr100K_words32K.bin from COLMAP's releases; you "
                        "download it, dars never downloads anything). Without it, long sequential captures get no "
                        "loop closure")
    q.add_argument("--min-registered", type=float, default=d.min_registered, metavar="FRACTION",
                   help=f"fail when fewer than this fraction of the photos register (default: {d.min_registered})")
    q.add_argument("--no-upright", action="store_true", help="keep COLMAP's orientation (default: rotate world up to +z)")
    q.add_argument("--resume", action="store_true",
                   help="reuse the features, matches and model already in SCENE_DIR (made by an earlier dars poses)")
    q.add_argument("--force", action="store_true",
                   help="start again in a dars scene folder (deletes its outputs), or write into a non-empty folder "
                        "dars did not make (beside your files, never over them)")
    q.add_argument("--threads", type=int, default=d.num_threads, help="CPU threads for COLMAP (default: all cores)")
    q.add_argument("--seed", type=int, default=d.seed, help=f"random seed (default: {d.seed})")
    q.add_argument("--colmap-log", action="store_true", help="show COLMAP's own log on stderr")
    q.add_argument("--json", action="store_true", help="print the result as JSON on stdout (logs go to stderr)")
    q.add_argument("--quiet", action="store_true", help="no progress bars and no log lines")
    q.set_defaults(func=cmd_poses)


def cmd_poses(args: argparse.Namespace) -> int:
    from ..poses import PosesConfig, estimate_poses

    cfg = PosesConfig(matcher=args.matcher, max_size=args.max_size, camera_model=args.camera_model,
                      single_camera=args.single_camera, overlap=args.overlap, vocab_tree=args.vocab_tree,
                      min_registered=args.min_registered, upright=not args.no_upright, resume=args.resume,
                      force=args.force, num_threads=args.threads, seed=args.seed,
                      progress=not (args.quiet or args.json), colmap_log=args.colmap_log)

    def log(msg: str) -> None:
        if not args.quiet:
            _log_line(msg)

    result = estimate_poses(args.photos, args.out, cfg, log=log)
    if args.json:
        print_json(result.to_json())
    return 0
