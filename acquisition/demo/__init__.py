"""``mirrorgonio demo``: the whole chain on simulated devices, as a lab runs it.

1. A fresh data folder (``demo-data/YYYYmmdd-HHMMSS/``) with a ``daemon.toml``: the
   simulated rig (the simulated stage served over Modbus TCP on loopback and driven by the
   real ``ModbusArm``, the simulated camera writing DNG files), on a free loopback port,
   with a random API token (:mod:`acquisition.demo.folder`).
2. ``mirrorgonio serve`` and ``mirrorgonio worker`` as child processes, each in its own
   session (a Ctrl-C in the terminal reaches only this program, which stops them in
   order); on Linux they also get SIGTERM should this program die
   (:mod:`acquisition.demo.processes`).
3. The default light sweep through the REST API (``POST /runs`` with the token), followed
   with a progress bar; then ``POST /runs/{id}/process``, and the worker's job followed
   the same way. The worker finds the sources in the data, as it would for a lab's
   unknown lamp (``truth_layout=True`` gives it the simulated truth's layout instead)
   (:mod:`acquisition.demo.run`).
4. The worker and the daemon are stopped (SIGTERM, then SIGKILL of their whole process
   group if they linger), also on Ctrl-C or an error: no process is left behind.
5. The light model the worker wrote is scored against the simulated truth as
   ``mirrorgonio bench accuracy`` scores it: ``RMS(I_fit − I_true) / max(I_true)`` per
   source over the θ range its samples cover (:mod:`acquisition.demo.truth`), and the
   result summarised (:mod:`acquisition.demo.summary`).
"""

from acquisition.demo.folder import MARKER, new_data_dir
from acquisition.demo.processes import DemoError
from acquisition.demo.run import DEMO_RIG_PATH, run_demo
from acquisition.demo.summary import DemoResult, print_summary

__all__ = ["DEMO_RIG_PATH", "MARKER", "DemoError", "DemoResult", "new_data_dir", "print_summary", "run_demo"]
