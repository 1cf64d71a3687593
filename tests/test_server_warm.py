"""A server loads the finish step's kernels (numba, depth) while its first job's images arrive,
not between that job's last tile and done (where it cost the first job ~0.9 s)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

# in a fresh interpreter: "loaded before" must see a process where nothing loaded numba yet
CODE = """
import sys, threading
from maxfs.service.http.jobs import JobManager
from maxfs.service.settings import Settings
from maxfs.storage.layout import JobSpec
from maxfs.storage.params import JobParams
from maxfs.storage.tokens import User
from maxfs.worker import synthetic

print("before", "numba" in sys.modules)
m = JobManager(Settings(data_dir=sys.argv[1]))
m.root.mkdir(parents=True)
spec = JobSpec(k=4, height=8, width=8, channels=None, dtype="uint8",
               lights=synthetic.lights_uniform(4).tolist())
started = []
for depth in ("none", "ls", "ls", "bini"):  # a job without depth loads nothing: the next one does
    m.create(spec, JobParams.build(eps=1.0, tile=16, depth=depth), User("alice"))
    started += [t for t in threading.enumerate() if t.name == "maxfs-warm-finish" and t not in started]
for t in started:
    t.join(120)
from maxfs.worker import depth_solver
print("threads", len(started), "kernels", len(depth_solver._grid_links.signatures))
"""


def test_the_first_job_loads_the_depth_kernels_once_on_a_thread(tmp_path: Path) -> None:
    r = subprocess.run(
        [sys.executable, "-c", CODE, str(tmp_path / "data")], capture_output=True, text=True, timeout=180
    )
    assert r.returncode == 0, r.stderr[-2000:]
    lines = r.stdout.split("\n")
    assert lines[0] == "before False", r.stdout  # importing the job manager loads no numba
    _, threads, _, kernels = lines[1].split()
    assert threads == "1", r.stdout  # one thread for the four jobs
    assert int(kernels) >= 1, r.stdout  # the depth kernels are loaded (from numba's cache)
