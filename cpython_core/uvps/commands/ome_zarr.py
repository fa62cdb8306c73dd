"""``uvps ome-zarr RUN``: a run folder's depth, normals and albedo as OME-Zarr pyramids
(:func:`uvps.files.omezarr.write_ome_zarr`)."""
from __future__ import annotations

from pathlib import Path

from ..errors import UVPSInputError
from ..files.omezarr import NGFF_VERSION, write_ome_zarr
from ..files.outputs import CommandResult, OutputSpec
from ..spec import CommandSpec, Param


def _cmd_ome_zarr(inputs, params, output_dir, *, progress=None):
    """``ome-zarr``: the OME-Zarr pyramids of an existing run folder, written into it."""
    run_dir = Path(inputs["run"])
    if not run_dir.is_dir():
        raise UVPSInputError(f"run folder {run_dir} does not exist or is not a folder")
    stores = write_ome_zarr(run_dir, pixel_size_um=params["pixel_size_um"], progress=progress)
    outputs = [OutputSpec(s.name.split(".")[0] + "_zarr", str(s), kind="folder") for s in stores]
    return CommandResult(outputs, {"ngff_version": NGFF_VERSION, "stores": [str(s) for s in stores]}, [],
                         text="\n".join(str(s) for s in stores))


SPECS = (
    CommandSpec("ome-zarr", "a run folder's depth, normals and albedo as OME-Zarr pyramids", _cmd_ome_zarr,
                output="", params=(
                    Param("run", "path", where="inputs", positional=True, required=True, label="Run folder",
                          help="the run folder whose depth.tif, normals.tif and albedo.tif to convert"),
                    Param("pixel_size_um", "float", minimum=0, exclusive_minimum=True, unit="um",
                          help="pixel size (default: the TIFFs' calibration)")),
                description="Writes depth.ome.zarr, normals.ome.zarr and albedo.ome.zarr (with the protrusion "
                            "and colour-area labels) into the run folder: OME-NGFF 0.4 multiscale images for "
                            "napari, BigDataViewer/MoBIE and web viewers; `uvps run --ome-zarr` does the same "
                            "as part of a run."),
)
