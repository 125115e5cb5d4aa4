"""Domain exceptions. The CLI turns each into one line on stderr and its exit code.

Exit codes (documented in docs/bad-input.md):
    0  success
    1  unexpected internal error (a bug: please report it with --debug output)
    2  bad command line (argparse)
    3  invalid input: a dataset, predictions or candidates file breaks the contract
    4  the data cannot be solved (too few poses, degenerate motion, no overlap)
    5  output could not be written
"""


class Calib3rError(Exception):
    exit_code = 1


class InputError(Calib3rError):
    """A file breaks the contract. ``str(e)`` is ``"<path>[: <where>]: <what>"``."""

    exit_code = 3

    def __init__(self, path, what: str, where: str | None = None):
        self.path, self.what, self.where = str(path), what, where
        loc = f"{self.path}: {where}" if where else self.path
        super().__init__(f"{loc}: {what}")


class SolveError(Calib3rError):
    exit_code = 4


class OutputError(Calib3rError):
    exit_code = 5


# --- exceptions from the libraries (GTSAM, pycolmap, OpenCV) as one line ---------------------------

LIBRARIES = {"gtsam": "GTSAM", "pycolmap": "pycolmap", "cv2": "OpenCV"}
# what a GTSAM key's letter stands for (solve's graph and pattern-ba's)
_SYMBOLS = {"x": "a view's pose", "s": "a view's depth scale", "c": "a view's depth correction",
            "e": "a camera's ee_T_cam", "l": "a camera's metric scale", "v": "a view's pose",
            "b": "the board's pose", "q": "the board's scale", "k": "a camera's intrinsics"}


def _library_of(exc) -> str | None:
    """Which library raised ``exc``: by its type's module, by the library's own Python frames in the
    traceback, or by the library objects named on the line of our code that called into it."""
    import linecache
    import re

    mod = type(exc).__module__.split(".")[0]
    if mod in LIBRARIES:
        return mod
    tb, innermost = exc.__traceback__, None
    while tb is not None:
        fname = tb.tb_frame.f_code.co_filename.replace("\\", "/")
        for lib in LIBRARIES:
            if f"/{lib}/" in fname:
                return lib
        innermost = tb
        tb = tb.tb_next
    if innermost is None:
        return None
    frame = innermost.tb_frame
    line = linecache.getline(frame.f_code.co_filename, innermost.tb_lineno)
    for name in re.findall(r"[A-Za-z_]\w*", line):
        value = frame.f_locals.get(name, frame.f_globals.get(name))
        if value is None:
            continue
        owner = value.__name__ if type(value).__name__ == "module" else type(value).__module__
        owner = (owner or "").split(".")[0]
        if owner in LIBRARIES:
            return owner
    return None


def library_error(exc, describe=None) -> tuple[str, int] | None:
    """``(one line, exit code)`` for an exception raised by GTSAM, pycolmap or OpenCV, else None.

    The line names the library and the cause (OpenCV's error name and first detail, GTSAM's
    under-constrained variable and what it is); the full text is left to ``--debug``.
    ``describe(letter, index) -> str | None`` names a GTSAM key in the caller's words (the view's
    camera and frame: solver.graph.Keys.describe), instead of the key and its kind."""
    import re

    lib = _library_of(exc)
    if lib is None:
        return None
    text = str(exc)
    lines = [line.strip(" >") for line in text.splitlines() if line.strip(" >")]
    if lib == "gtsam" and "ndetermina" in text:
        m = re.search(r"Symbol: (\w)(\d+)", text)
        named = describe(m.group(1), int(m.group(2))) if m and describe else None
        var = (f" near {named}" if named else
               f" near variable {m.group(1)}{m.group(2)} ({_SYMBOLS.get(m.group(1), 'a variable')})" if m else "")
        return (f"GTSAM: indeterminate linear system{var}: nothing fixes it well enough (too little overlap or "
                "rotation in the data, or a zero or non-finite noise sigma)", SolveError.exit_code)
    if lib == "cv2":
        m = re.search(r"error: \(-?\d+:([^)]*)\)([^\n]*)", text)
        cause = m.group(1) if m else (lines[0] if lines else type(exc).__name__)
        # the detail: on the lines below (a Python binding's message) or after the cause on its line
        detail = next((line for line in lines[1:] if not line.startswith(("where", "'"))), "")
        detail = detail or (m.group(2).strip() if m else "")
        return f"OpenCV: {cause}" + (f" ({detail})" if detail else ""), 1
    first = lines[0] if lines else type(exc).__name__
    return f"{LIBRARIES[lib]}: {type(exc).__name__}: {first}", 1
