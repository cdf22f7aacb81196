"""The I/O layer: the only place that touches files. Kernels elsewhere are pure."""
