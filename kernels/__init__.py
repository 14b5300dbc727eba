"""OpenCL C sources of cm2cl, one file per concern (shipped as package data)."""
