"""omg4: Optimized Minimal 4D Gaussian Splatting (OMG4, ICLR 2026) on Real-Time4DGS.

Train the Real-Time4DGS baseline from multi-view video, compress it with every OMG4 stage
into one ``.omg4`` file, decode that file alone, render and evaluate it.
"""

__version__ = "0.1.0"
