"""pcc_ros: LiDAR vehicle shape completion and shape-based detection filtering for ROS 2.

``import pcc_ros`` must stay light and must never need ROS: heavy libraries (torch,
open3d, rosbags) are imported by the modules that use them, and rclpy only inside
``pcc_ros.nodes``.

One process-wide setting is made here, before anything can load torch: libgomp (torch's
OpenMP runtime on Linux) keeps its worker threads spinning for ``GOMP_SPINCOUNT`` iterations
after every parallel region -- 300000 by default, several milliseconds -- so after the network
the idle torch worker holds a core that the filter's second thread and the node's own
threads then wait for (at 20 cars the filter stage took 8.5 instead of 5.6-5.8 ms; docs/nodes.md,
"CPU threads and OpenMP's spin").
:data:`GOMP_SPINCOUNT` keeps the spin short enough to give the core back and long enough
for the network's back-to-back operators (measured: the completion stage as fast as with the
default). A value the user set is kept, and so is an ``OMP_WAIT_POLICY`` the user set (libgomp
takes ``GOMP_SPINCOUNT`` over the policy's spin, so setting it would undo ``passive`` or
``active``); set before torch is imported, or it has no effect; child processes inherit it, as
any environment variable.

A second one, for the same reason: OpenBLAS (numpy's and SciPy's BLAS in the pip wheels; the
networks' compiled CPU loops reach SciPy's through numba, :mod:`pcc_ros.models.kernels`)
starts a helper thread per core when it loads and splits every product over them; a product
split that way waits for its helpers, and on a machine whose other cores are busy the wait
costs more than the product (measured: 6 against 140 GFLOP/s at 1024 x 128 @ 128 x 256, the
other core loaded; a batch of 32 cars took 3.2 s instead of 26 ms). The completers get their
parallelism from their ``workers`` instead, so :data:`OPENBLAS_NUM_THREADS` is 1 unless the user
set a count; OpenBLAS reads it once, when it loads (after ``import pcc_ros`` in every entry
point; a program that loaded numpy's or SciPy's BLAS before keeps its own count).
"""

import os

__version__ = "0.1.0"

#: libgomp spin iterations after a parallel region (its default: 300000); see the module doc.
GOMP_SPINCOUNT = "10000"

if "OMP_WAIT_POLICY" not in os.environ:  # the user chose the spin already
    os.environ.setdefault("GOMP_SPINCOUNT", GOMP_SPINCOUNT)

#: OpenBLAS threads per calling thread (see the module doc).
OPENBLAS_NUM_THREADS = "1"

os.environ.setdefault("OPENBLAS_NUM_THREADS", OPENBLAS_NUM_THREADS)
