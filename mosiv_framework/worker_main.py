"""The child side of :func:`mosiv_framework.workers.run_jobs`: one job in one process.

``python -X faulthandler -m mosiv_framework.worker_main FOLDER`` reads ``FOLDER/job.pkl``
(the parent's import path, then the pickled function and arguments), runs the job and leaves
``result.pkl`` or, if it raised, ``error.pkl`` (the exception; its traceback is printed to the
job's output). Neither file means the process died, which the parent reports and retries.
"""

from __future__ import annotations

import os
import pickle
import sys
import traceback
from pathlib import Path


def _write(path: Path, value: object) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(pickle.dumps(value))
    os.replace(tmp, path)  # the parent never reads half a file


def main(folder: str) -> int:
    from mosiv_framework.logs import configure_from_environment

    configure_from_environment()  # the job's log records reach its log like the parent's
    job = Path(folder)
    import_path, payload = pickle.loads((job / "job.pkl").read_bytes())
    sys.path[:0] = [p for p in import_path if p not in sys.path]
    fn, args = pickle.loads(payload)
    try:
        result = fn(*args)
    except Exception as error:
        traceback.print_exc()
        sys.stdout.flush()
        try:
            # an exception can pickle and yet not unpickle (keyword-only ``__init__``): the
            # parent would then fail on reading it and take every other job down with it
            pickle.loads(pickle.dumps(error))
            _write(job / "error.pkl", error)
        except Exception:  # an exception that does not travel still reaches the parent
            _write(job / "error.pkl", RuntimeError(f"{type(error).__name__}: {error}"))
        return 1
    _write(job / "result.pkl", result)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
