"""Frontends: from images (and depth) to ``predictions/<name>/``.

* ``rgbd``   — sensor depth as canonical metric depth + SIFT matches (OpenCV), verified.
* ``colmap`` — pycolmap features, matching, two-view geometry and incremental mapping;
  sparse depth from triangulated tracks; COLMAP's poses usable as initialisation.
* ``foundation`` — converters from files saved where VGGT / MASt3R / DUSt3R run.
"""

from calib3r_graph.errors import InputError


def best_frontend(ds) -> str:
    """rgbd where depth exists, else colmap."""
    return "rgbd" if ds.has_depth() else "colmap"


def run_frontend(ds, frontend: str, name: str | None = None, progress: bool = True, **kw) -> str:
    """Run a frontend on a dataset and write predictions/<name>/; returns the name."""
    name = name or frontend
    if frontend == "rgbd":
        from calib3r_graph.frontends.rgbd import predict_rgbd

        predict_rgbd(ds, name, progress=progress, **kw)
    elif frontend == "colmap":
        from calib3r_graph.frontends.colmap import predict_colmap

        predict_colmap(ds, name, progress=progress, **kw)
    else:
        raise InputError("--frontend", f"unknown frontend '{frontend}' (rgbd or colmap)")
    return name
