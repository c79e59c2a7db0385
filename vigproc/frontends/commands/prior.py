"""``vigproc prior fit``, ``fit-scene`` and ``fit-lens-family``: fit the priors the estimators use
(the paper's natural-image prior, the scene fall-off, the lens family)."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from vigproc.atomic import atomic_write_text
from vigproc.core.estimate import estimate
from vigproc.core.prior import fit_prior
from vigproc.core.robust import RobustSettings
from vigproc.core.scene import fit_scene_falloff
from vigproc.errors import VigprocError
from vigproc.frontends.commands._progress import _progress
from vigproc.io.images import read_image
from vigproc.io.protocol import read_protocol_images
from vigproc.pipeline.processor import images_in as _images_in, output_file
from vigproc.stores.lensfun import lensfun_family

log = logging.getLogger("vigproc")


def cmd_prior_fit(args: argparse.Namespace) -> int:
    """``prior fit FOLDER``: the natural-image prior of Lyu 2010 (:func:`vigproc.core.prior.fit_prior`)
    from vignetting-free photos (unreadable ones skipped, with a warning)."""
    output_file(args.output)
    files = _images_in(Path(args.folder), args.limit)

    def images():
        for f in files:
            try:
                yield read_image(f, transfer=args.input_transfer)[0]
            except VigprocError as exc:
                log.warning("skipping %s", exc)

    source = args.source or f"vigproc prior fit {args.folder} --blocks-per-image {args.blocks_per_image} --seed {args.seed}"
    prior = fit_prior(images(), blocks_per_image=args.blocks_per_image, seed=args.seed, source=source)
    prior.save(args.output)
    print(f"fitted on {prior.n_blocks} blocks ({len(files)} images) -> {args.output}")
    return 0


def _fit_falloff(args: argparse.Namespace, what: str, source: str, estimate_with, iterations: int) -> int:
    """Fit a mean fall-off (:func:`vigproc.core.scene.fit_scene_falloff`) on a folder's photos
    in the benchmarks' framing (3:2 landscape, 480x320, linear luminance) and write it."""
    output_file(args.output)
    ims = read_protocol_images(_progress(_images_in(Path(args.folder), args.limit), "reading"), args.input_transfer)
    fitted = fit_scene_falloff(ims, estimate_with, iterations=iterations, source=source)
    atomic_write_text(Path(args.output), json.dumps(fitted.to_dict(), indent=1) + "\n")
    print(f"{what} from {fitted.n_images} photos: {fitted.field_ev_rms:.3f} EV RMS, "
          f"photos scatter {fitted.scatter_ev:.3f} EV around it -> {args.output}")
    return 0


def cmd_prior_fit_scene(args: argparse.Namespace) -> int:
    """``prior fit-scene FOLDER``: the scene fall-off prior of the robust estimator
    (:mod:`vigproc.core.scene`), refitted ``--iterations`` times."""
    source = (f"vigproc prior fit-scene {args.folder} --iterations {args.iterations} "
              f"--input-transfer {args.input_transfer}")
    return _fit_falloff(args, "scene fall-off", source,
                        lambda im, sc: estimate(im, "robust", channel_axis=None, settings=RobustSettings(scene=sc)),
                        args.iterations)


def cmd_prior_fit_lens_family(args: argparse.Namespace) -> int:
    """The lens family (vigproc.core.lensfamily) from a lensfun database's calibrations."""
    fam = lensfun_family(n_components=args.components, db_paths=args.db or None)
    fam.save(Path(args.output))
    errs = ", ".join(f"{k + 1}: {e:.4f}" for k, e in enumerate(fam.reconstruction_by_k))
    print(f"wrote {args.output}: {fam.coefficients.shape[0]} calibrations of {fam.lenses} lenses; "
          f"median reconstruction error by components (EV) {errs}")
    return 0
