"""Only for the optional compiled parts: the core's twin (service/_kernel.c) and the log scanner replay uses
(clients/_mcapscan.c); everything else is in pyproject.toml.

optional=True: without a C compiler the install still succeeds and the pure-Python code is used.
-ffp-contract=off: no fused multiply-add, so the kernel stays bit-identical to the Python reference.
"""

from setuptools import Extension, setup

FLAGS = ["-O2", "-ffp-contract=off", "-fno-fast-math", "-std=c11"]

setup(ext_modules=[Extension("service._kernel", ["service/_kernel.c"], optional=True, extra_compile_args=FLAGS),
                   Extension("clients._mcapscan", ["clients/_mcapscan.c"], optional=True, extra_compile_args=FLAGS)])
