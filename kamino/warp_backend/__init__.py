"""The Warp production backend (kernels, CUDA graphs, JAX interop): docs/warp_backend.md."""
