"""The file layer: captures and light files read, ImageJ TIFFs, run folders and OME-Zarr stores written,
every output written atomically. It calls the numeric library (:mod:`uvps.core`), never a command."""
