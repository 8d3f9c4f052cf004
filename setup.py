"""The optional C extensions of the hot path; everything else is in pyproject.toml.

- ``ambhil.bridge.protocol._wire``: the wire codec (bridge/protocol/wire.py falls back to its pure-Python twin without it);
- ``ambhil.bridge.process._deadline``: the real-time loop's receive deadline (bridge/process/deadline.py; without it a
  callback queue).

Both are ``optional``: without a C compiler the install goes on without them.
"""
import warnings

from setuptools import Extension, setup

# setuptools' note on every editable install ("be careful with folders in your working directory
# with the same name as your package") is information only: here the packages are those folders
warnings.filterwarnings("ignore", message="Editable installation")

setup(ext_modules=[
    Extension("ambhil.bridge.protocol._wire", ["bridge/protocol/_wire.c"], optional=True, extra_compile_args=["-O2"]),
    Extension("ambhil.bridge.process._deadline", ["bridge/process/_deadline.c"], optional=True, extra_compile_args=["-O2"],
              libraries=["pthread"]),
])
