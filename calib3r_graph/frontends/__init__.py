"""Frontends: from images (and depth) to ``predictions/<name>/``.

* ``rgbd``   — sensor depth as canonical metric depth + SIFT matches (OpenCV), verified.
* ``colmap`` — pycolmap features, matching, two-view geometry and incremental mapping;
  sparse depth from triangulated tracks; COLMAP's poses usable as initialisation.
* ``pairwise`` — RGB only, no global mapper: two-view geometry and triangulation per pair,
  each pair's scale aligned per view, aggregated with confidence (eq. 1).
* ``foundation`` — converters from files saved where VGGT / MASt3R / DUSt3R run.
"""

from calib3r_graph.errors import InputError

FRONTENDS = ("rgbd", "colmap", "pairwise")


def best_frontend(ds) -> str:
    """rgbd where depth exists, else pairwise: on the real recordings it solves every random subset
    of 6-10 views, where COLMAP's mapper often registers too few, and matches colmap on the full
    recordings (docs/few-views.md)."""
    return "rgbd" if ds.has_depth() else "pairwise"


def ensure_predictions(ds, requested: str | None = None, progress: bool = True, announce=None) -> str:
    """The name of the predictions to solve from: the one requested, the dataset's own, or, when it has
    none, the best frontend's (``best_frontend``), made now and cached in ``predictions/<frontend>/``.
    ``announce(line)`` is told which frontend runs (default: the log). Used by ``solve`` and ``compare``."""
    import logging

    from calib3r_graph.io.predictions import available_predictions, choose_predictions

    if requested is None and not available_predictions(ds.root):
        frontend = best_frontend(ds)
        line = (f"no predictions: making them with the '{frontend}' frontend"
                f"{' (depth/ present)' if frontend == 'rgbd' else ' (no depth/)'}, cached in "
                f"{ds.root / 'predictions' / frontend}")
        (announce or logging.getLogger(__name__).info)(line)
        run_frontend(ds, frontend, progress=progress)
    return choose_predictions(ds, requested)


def run_frontend(ds, frontend: str, name: str | None = None, progress: bool = True, **kw) -> str:
    """Run a frontend on a dataset and write predictions/<name>/; returns the name."""
    name = name or frontend
    if frontend == "rgbd":
        from calib3r_graph.frontends.rgbd import predict_rgbd

        predict_rgbd(ds, name, progress=progress, **kw)
    elif frontend == "colmap":
        from calib3r_graph.frontends.colmap import predict_colmap

        predict_colmap(ds, name, progress=progress, **kw)
    elif frontend == "pairwise":
        from calib3r_graph.frontends.pairwise import predict_pairwise

        predict_pairwise(ds, name, progress=progress, **kw)
    else:
        raise InputError("--frontend", f"unknown frontend '{frontend}' ({', '.join(FRONTENDS)})")
    return name
