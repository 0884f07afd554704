"""The tables' schemas across versions: a column added later reads as null on tables written before it; any
other missing column is an error that names it."""

import pyarrow.parquet as pq
import pytest

from aerocal import tables
from aerocal.simulate import simulate_flight


def test_an_images_table_written_before_the_laser_column_reads_with_it_null(tmp_path):
    images = simulate_flight("conte-calibration", seed=2, max_images=4).images
    earlier = images.drop_columns(["laser_range_m"])
    path = tmp_path / "images.parquet"
    pq.write_table(earlier, path)
    back = tables.read(path, "images")
    assert back.schema.names == tables.SCHEMAS["images"].names
    assert back.column("laser_range_m").null_count == back.num_rows == 4
    with pytest.raises(tables.SchemaError, match="gnss_x"):
        tables.validate(earlier.drop_columns(["gnss_x"]), "images", source="images.parquet")
