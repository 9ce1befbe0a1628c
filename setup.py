"""Only for the optional compiled parts; everything else is in pyproject.toml.

service._kernel, one extension from one source per layer: the core's twin (service/core/kernel.c), the plant's
integrator (service/plant/rk4.c), a network's (service/plant/network.c) and the daemon's tick writer
(service/daemon/tickwriter.c), sharing service/core/kernel.h. service.logio._mcapscan: the scanner replay uses on
our own logs. service._stopsignal: a stop signal that arms SIGALRM without needing the interpreter (clients.live).

optional=True: without a C compiler the install still succeeds and the pure-Python code is used.
-ffp-contract=off: no fused multiply-add, so the kernel stays bit-identical to the Python reference.
"""

from setuptools import Extension, setup

FLAGS = ["-O2", "-ffp-contract=off", "-fno-fast-math", "-std=c11"]
KERNEL = ["service/kernel_module.c", "service/core/kernel.c", "service/plant/rk4.c", "service/plant/network.c",
          "service/daemon/tickwriter.c"]

setup(ext_modules=[Extension("service._kernel", KERNEL, include_dirs=["service/core"],
                             depends=["service/core/kernel.h"], optional=True, extra_compile_args=FLAGS),
                   Extension("service.logio._mcapscan", ["service/logio/_mcapscan.c"], optional=True,
                             extra_compile_args=FLAGS),
                   Extension("service._stopsignal", ["service/stopsignal.c"], optional=True,
                             extra_compile_args=["-O2", "-std=c11"])])
