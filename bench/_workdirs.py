"""The folders every benchmark that prepares data takes: ``--work`` (prepared datasets), ``--cache``
(frontend caches, reused between runs) and ``--out`` (the figures, default bench/results)."""

from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def add_work_args(ap, name: str):
    ap.add_argument("--work", default=f"/tmp/{name}")
    ap.add_argument("--cache", default=f"/tmp/{name}/cache")
    ap.add_argument("--out", default=str(RESULTS))


def work_dirs(args) -> tuple[Path, Path, Path]:
    """(work, cache, out), with work and out created."""
    work, cache, out = Path(args.work), Path(args.cache), Path(args.out)
    for d in (work, out):
        d.mkdir(parents=True, exist_ok=True)
    return work, cache, out
