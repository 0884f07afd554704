"""Products of an adjusted block: the surface model and the orthomosaic a GIS opens.

:mod:`dense` matches the adjusted frames pair by pair (semi-global matching on rectified pairs) and fuses the
depths across views into a dense cloud, which :mod:`pointcloud` writes as LAZ; :mod:`dsm` grids the dense cloud
(or, without frames, the block's tie points) into a digital surface model, and :mod:`terrain` filters the
ground out of it (a DTM), both left without heights where :mod:`coverage` finds that no frame sees the ground;
:mod:`mosaic` rectifies every frame on that surface into an orthomosaic (counts and, where the frames are
radiometric, temperature) as cloud-optimised GeoTIFFs, in tiles that run on a Dask cluster; :mod:`kernels`
holds its numeric inner loops; :mod:`range_check` compares the surface with the frames' laser ranges. Inputs are
the pipeline's tables (poses, points, cameras); nothing here estimates geometry.

Tests: tests/test_dense.py, tests/test_dsm.py, tests/test_mosaic.py, tests/test_range_check.py.
"""
