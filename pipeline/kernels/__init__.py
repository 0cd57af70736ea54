"""Pure NumPy/SciPy kernels: arrays in, arrays out; nothing else from the package is imported here."""
