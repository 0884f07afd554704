"""Products of an adjusted block: the surface model and the orthomosaic a GIS opens.

:mod:`dsm` grids the block's points (and the dense surface when it exists) into a digital surface model;
:mod:`mosaic` rectifies every frame on that surface into an orthomosaic (counts and, where the frames are
radiometric, temperature) as cloud-optimised GeoTIFFs, in tiles that run on a Dask cluster; :mod:`kernels`
holds its numeric inner loops. Inputs are the pipeline's tables (poses, points, cameras); nothing here
estimates geometry.
"""
