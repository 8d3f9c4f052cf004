"""The optional C extensions of the hot path; everything else is in pyproject.toml.

- ``ambhil.bridge.protocol._wire``: the wire codec and the lockstep loops' ordinary steps (bridge/protocol/wire.py
  falls back to its pure-Python twin without it);
- ``ambhil.bridge.process._deadline``: the real-time loop's receive deadline (bridge/process/deadline.py; without it a
  callback queue).

Both are ``optional``: without a C compiler the install goes on without them.
"""
import warnings

from setuptools import Extension, setup

# setuptools' note on every editable install ("be careful with folders in your working directory
# with the same name as your package") is information only: here the packages are those folders
warnings.filterwarnings("ignore", message="Editable installation")

setup(
    # the C ABI of laws, for a user's firmware build: <prefix>/include/ambhil_law.h
    # (`cc -I"$(python -c 'import sys; print(sys.prefix)')/include" ...`)
    data_files=[("include", ["include/ambhil_law.h"])],
    ext_modules=[
    # one module of two concepts: the codec (_wire.c) and the lockstep loops (_lockstep.c and the
    # two types' files); what they share is in _wire.h / _lockstep.h (MANIFEST.in ships the headers)
    Extension("ambhil.bridge.protocol._wire",
              ["bridge/protocol/_wire.c", "bridge/protocol/_lockstep.c", "bridge/protocol/_plant_lockstep.c",
               "bridge/protocol/_controller_lockstep.c"],
              depends=["bridge/protocol/_wire.h", "bridge/protocol/_lockstep.h", "bridge/protocol/_blake2b.h"],
              optional=True, extra_compile_args=["-O2"]),
    Extension("ambhil.bridge.process._deadline", ["bridge/process/_deadline.c"], optional=True, extra_compile_args=["-O2"],
              libraries=["pthread"]),
])
