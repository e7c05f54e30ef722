"""The napari plugin: readers for movies and calibrations, and the calibrate, localize and
render widgets (declared in ``sparseloc/napari.yaml``).

napari, Qt and magicgui are imported only inside this subpackage (the ``napari`` extra).
Every widget calls the same library functions as the command line; none holds solver code.
"""
