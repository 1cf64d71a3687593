"""maxfs-ps: robust calibrated photometric stereo by exact maximum feasible Lambertian subsystems.

The Python face of the project (Yu, Seo, Lee, ECCV 2010: per pixel, the largest set of images
that obey the Lambertian law within eps, found exactly, then a least-squares refit):

* :func:`solve_folder` - a dataset folder, as ``maxfs run`` solves it;
* :func:`solve` - an image stack in memory (numpy);
* :func:`open_result` - a job store written by ``maxfs run -o`` or fetched from a server;

each returning a :class:`Result` of numpy arrays (``normal``, ``albedo``, ``inliers``, ``source``,
``depth``) with :meth:`Result.to_xarray`. The installed subpackages are ``maxfs.storage`` (formats
on disk), ``maxfs.worker`` (the solvers) and ``maxfs.service`` (the CLI, the HTTP server and the
job runners). Importing ``maxfs`` loads neither the solver nor the server.
"""

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from maxfs.api import Result, open_result, solve, solve_folder

__all__ = ["Result", "open_result", "solve", "solve_folder"]
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    """The public names, from :mod:`maxfs.api` on first use: importing the package itself costs
    nothing (the ``maxfs`` script imports it first, and a Ctrl-C then gets a line, not numpy's
    import traceback: :mod:`maxfs.service.cli.entry`)."""
    if name in __all__:
        from maxfs import api

        return getattr(api, name)
    raise AttributeError(f"module 'maxfs' has no attribute {name!r}")
