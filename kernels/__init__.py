"""OpenCL C sources of the engine, installed as ``clsplat.kernels``: one file per stage plus
``common.h`` (shared maths and the named constants). Read them with importlib.resources."""
