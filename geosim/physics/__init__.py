"""Pure physics kernels: transfer functions (optics, detector, atmosphere, motion,
off-nadir view, resampling) and radiometric effects (haze, colour, noise,
compression). No file I/O here."""
