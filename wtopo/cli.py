# SPDX-License-Identifier: Apache-2.0
"""The ``wtopo`` command: ``fit``, ``scenes``, ``report``, ``export``.

Examples::

    wtopo --version
    wtopo scenes
    wtopo fit bunny --out runs/bunny
    wtopo fit path/to/dataset --out runs/x --iterations 2000 --device cuda
    wtopo fit path/to/photos --out runs/p    # images only: camera poses by structure from motion
    wtopo fit bunny --out runs/b --set losses.mask=0.5 --set mesh.sigma=0.5
    wtopo report runs/bunny
    wtopo export runs/bunny runs/bunny/final.obj
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import warnings

__all__ = ["main", "build_parser"]

# Errors a user causes and can fix (a bad path, flag, config value or dataset): reported as one line
# ``wtopo <command>: error: ...`` with exit code 2, as argparse reports a bad flag. OSError covers
# unreadable files, permissions and a full disk. Anything else is a bug and keeps its traceback;
# ``--traceback`` shows it for these too. ModuleNotFoundError: an optional dependency the input needs
# is missing (pycolmap for a folder of photos); the message says what to install.
_USER_ERRORS = (ValueError, TypeError, OSError, ModuleNotFoundError)
_USAGE_ERROR = 2  # argparse's exit status for a usage error


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, as every other user error of the command."""

    def error(self, message: str):
        self.exit(_USAGE_ERROR, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _load(scene: str, *, sfm: bool = False, progress: bool = True):
    from . import scenes

    if sfm and not os.path.isdir(scene):
        raise ValueError(f"--sfm takes a folder of photographs, got {scene!r}")
    if os.path.exists(scene):
        from .loaders import detect_format, load_scene

        fmt = "photos" if sfm else detect_format(scene)
        if fmt == "photos":  # structure from motion prints its plan and shows progress bars
            return load_scene(scene, format=fmt, progress=progress)
        return load_scene(scene, format=fmt)
    if scene in scenes.names():
        return scenes.load(scene)
    raise FileNotFoundError(f"{scene!r} is neither an existing path nor a built-in scene "
                            f"({', '.join(scenes.names())})")


# command-line flag -> (FitConfig section, field)
_OVERRIDES = (
    ("warmup", "warmup", "iterations"),
    ("coevolution", "coevolution", "iterations"),
    ("device", "runtime", "device"),
    ("seed", "runtime", "seed"),
    ("max_surfels", "runtime", "max_surfels"),
    ("usd_every", "runtime", "usd_every"),
    ("normal_flip", "mesh", "normal_flip"),
    ("samples_per_surfel", "mesh", "samples_per_surfel"),
    ("proxy_resolution", "mesh", "resolution"),
)


def _parse_value(text: str):
    """``--set`` value: JSON when it parses (numbers, true/false/null, lists), else the raw string."""
    import json

    try:
        return json.loads(text)
    except ValueError:
        return text


def _apply_set(cfg, item: str) -> None:
    """Apply one ``--set PATH=VALUE`` (dotted FitConfig path, e.g. ``losses.mask=0.5``)."""
    from .fitting.config import RemovedFieldError, set_field

    path, sep, text = item.partition("=")
    if not sep or not path:
        raise ValueError(f"--set takes PATH=VALUE (e.g. losses.mask=0.5), got {item!r}")
    try:
        set_field(cfg, path.strip(), _parse_value(text))
    except RemovedFieldError:
        raise  # names the field already, and keeps its type
    except ValueError as e:
        raise ValueError(f"--set: {e}") from None


def _config(args):
    import json

    from .fitting import FitConfig, Preset

    cfg = FitConfig.toposurfel_public() if args.recipe == "toposurfel-public" else FitConfig()
    if args.config is not None:
        try:
            with open(args.config) as fh:
                data = json.load(fh)
        except (OSError, ValueError) as e:
            raise ValueError(f"--config {args.config!r}: {e}") from None
        if not isinstance(data, dict):
            raise ValueError(f"--config {args.config!r} must hold a JSON object, got {type(data).__name__}")
        cfg = FitConfig.from_dict(data)
    if args.preset is not None:
        cfg.preset = Preset(args.preset)
    if args.iterations is not None:  # split evenly between warm-up and co-evolution
        w = args.iterations // 2
        cfg.warmup.iterations, cfg.coevolution.iterations = w, args.iterations - w
    for arg, section, name in _OVERRIDES:
        value = getattr(args, arg)
        if value is not None:
            setattr(getattr(cfg, section), name, value)
    if args.downscale is not None:  # one knob: the fit resizes its training images by runtime.image_scale
        if not math.isfinite(args.downscale) or args.downscale < 1:
            raise ValueError(f"--downscale must be a finite number >= 1, got {args.downscale!r}")
        cfg.runtime.image_scale = 1.0 / args.downscale
    if args.no_mesh_loop:
        cfg.coevolution.enabled = False
    if args.profile:
        cfg.runtime.profile = True
    for item in args.set or ():
        _apply_set(cfg, item)
    return cfg


def _cmd_fit(args) -> int:
    from .fitting import fit, validate_config

    cfg = _config(args)  # before the scene is loaded: a bad flag is reported at once
    validate_config(cfg)
    chunks = _chunks_arg(args.chunks)
    scene = _load(args.scene, sfm=args.sfm, progress=not args.quiet)
    if chunks is not None:
        return _fit_chunks(scene, cfg, args, chunks)
    result = fit(scene, cfg, out_dir=args.out, progress=not args.quiet)
    if args.quiet:
        r = result.report
        print(f"{r['status']}: {r['iterations']} iterations in {r['elapsed_s']:.1f} s, mesh {args.out}/mesh.ply")
    return 130 if result.report["status"] == "interrupted" else 0


def _chunks_arg(text: str | None):
    """``--chunks``: ``None`` (no chunking), ``"auto"`` (the plan decides) or a count >= 1."""
    if text is None or text == "auto":
        return text
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"--chunks takes a number of chunks >= 1 or 'auto', got {text!r}")
    return n


def _fit_chunks(scene, cfg, args, chunks) -> int:
    from .chunks import ChunkConfig, fit_chunked

    ccfg = ChunkConfig(chunks=None if chunks == "auto" else chunks, merge=args.chunk_merge)
    result = fit_chunked(scene, args.out, cfg, chunk_config=ccfg,
                         progress=not args.quiet)
    if result is not None and args.quiet:
        print(f"{result.report['chunks']} chunks in {result.report['wall_s']:.1f} s, mesh {args.out}/mesh.ply")
    return 0


def _cmd_scenes(args) -> int:
    from . import scenes

    for name in scenes.names():
        print(name)
    return 0


def _cmd_report(args) -> int:
    from .report import report

    for kind, path in report(args.run_dir).items():
        print(f"{kind}: {path}")
    return 0


def _cmd_export(args) -> int:
    from .io.export import export

    print(export(args.run_dir, args.out, args.format, iteration=args.iteration))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``wtopo`` command."""
    from . import __version__

    p = _Parser(prog="wtopo", description="Posed photographs to a watertight mesh.")
    p.add_argument("--version", action="version", version=f"wtopo {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--traceback", action="store_true",
                        help="show the traceback of an error instead of the one-line message")
    sub = p.add_subparsers(dest="command", required=True)

    f = sub.add_parser("fit", parents=[common],
                       help="fit a scene and write mesh.ply, surfels.ply, history/report/plan JSON")
    f.add_argument("scene", help="dataset path (Blender, COLMAP, DTU, nerfstudio, or a folder of photos) or a built-in "
                   "name (wtopo scenes)")
    f.add_argument("--out", required=True, help="run directory (resumes when it holds checkpoints)")
    f.add_argument("--iterations", type=int, help="warm-up and co-evolution iterations, split evenly (the plan's "
                   "polish comes on top)")
    f.add_argument("--warmup", type=int, help="warm-up iterations")
    f.add_argument("--coevolution", type=int, help="co-evolution iterations")
    f.add_argument("--device", help="auto, cpu or cuda:N")
    f.add_argument("--seed", type=int)
    f.add_argument("--max-surfels", type=int)
    f.add_argument("--usd-every", type=int, help="timeline sample interval (0: no timeline.usdc)")
    f.add_argument("--downscale", type=float, metavar="F",
                   help="train on images F times smaller (F >= 1; sets runtime.image_scale = 1 / F)")
    f.add_argument("--no-mesh-loop", action="store_true", help="co-evolution without the proxy mesh (ablation)")
    f.add_argument("--normal-flip", choices=["mesh", "view", "random"])
    f.add_argument("--samples-per-surfel", type=int, choices=[1, 5])
    f.add_argument("--proxy-resolution", type=int, metavar="N",
                   help="grid nodes per side of the co-evolving proxy mesh's Poisson solve (mesh.resolution)")
    f.add_argument("--preset", choices=["fast", "balanced", "best"],
                   help="quality against time (FitConfig.preset; default balanced): the plan's iterations, image "
                        "size and grids; explicit --set values still win")
    f.add_argument("--recipe", choices=["default", "toposurfel-public"], default="default",
                   help="toposurfel-public: start from the public TopoSurfel code's settings where supported")
    f.add_argument("--config", metavar="FILE.json",
                   help="start from a FitConfig saved as JSON (a run's config.json or FitConfig.to_dict())")
    f.add_argument("--set", action="append", metavar="PATH=VALUE",
                   help="set any FitConfig field by its dotted path, after the other flags (repeatable), "
                        "e.g. --set losses.mask=0.5 --set mesh.sigma=0.5")
    f.add_argument("--profile", action="store_true",
                   help="print the time per stage at the end (runtime.profile; report.json 'profile'); on CUDA "
                        "each stage then synchronises the device")
    f.add_argument("--sfm", action="store_true",
                   help="camera poses by structure from motion (pycolmap: pip install \"wtopo[sfm]\"), ignoring any "
                        "cameras the folder has; a folder with images and no cameras gets this without the flag. The "
                        "model is written to sparse/0 beside the images and reused by the next run")
    f.add_argument("--chunks", metavar="N|auto",
                   help="fit the region of interest as N overlapping chunks (auto: the plan decides from the views "
                        "and the memory) and merge them; under torchrun use python -m wtopo.chunks.run")
    f.add_argument("--chunk-merge", choices=("refuse", "weld"), default="refuse",
                   help="how chunks are merged: refuse (default) meshes the merged surfels once over the whole "
                        "region, no seam; weld joins the chunks' own meshes at the cuts")
    f.add_argument("--quiet", action="store_true", help="no plan, no progress bars")
    f.set_defaults(func=_cmd_fit)

    s = sub.add_parser("scenes", parents=[common], help="list the built-in scenes")
    s.set_defaults(func=_cmd_scenes)

    r = sub.add_parser("report", parents=[common], help="contact sheet and error plot of a run directory")
    r.add_argument("run_dir")
    r.set_defaults(func=_cmd_report)

    e = sub.add_parser("export", parents=[common], help="export a run's mesh, surfels or timeline")
    e.add_argument("run_dir")
    e.add_argument("out")
    e.add_argument("--format", help="mesh, surfels, ... (default: from the suffix)")
    e.add_argument("--iteration", type=int, help="latest timeline sample at or before this iteration")
    e.set_defaults(func=_cmd_export)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``wtopo`` script.

    Returns:
        The exit status: 0, 2 for a user error (printed as one line ``wtopo <command>: error: ...``
        on stderr), 130 for an interrupted fit. Other exceptions propagate with their traceback.
    """
    args = build_parser().parse_args(argv)

    def show_warning(message, category, filename, lineno, file=None, line=None):
        kind = "" if category is UserWarning else f"{category.__name__}: "
        print(f"wtopo {args.command}: warning: {kind}{message}", file=file or sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show_warning  # one line per warning, as the errors are
            return int(args.func(args) or 0)
    except _USER_ERRORS as e:
        if args.traceback:
            raise
        message = " ".join(str(e).split()) or type(e).__name__  # one line, even for multi-line messages
        print(f"wtopo {args.command}: error: {message}", file=sys.stderr)
        return _USAGE_ERROR


if __name__ == "__main__":
    sys.exit(main())
