"""pointmark: spectral watermarking of 3D point sets (Ohbuchi et al., 2004), for whole catalogues."""

__version__ = "0.2.0"
