"""Initial schema: cameras, certificates, flights, campaigns, runs, artifacts, lineage.

Revision ID: 0001
Revises:
Create Date: 2025-01-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

_TS = sa.DateTime(timezone=True)
_IMMUTABLE = "certificates are immutable: issue a new certificate that supersedes this one"


def upgrade() -> None:
    op.create_table(
        "cameras",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("make", sa.String(128), nullable=False),
        sa.Column("model", sa.String(128), nullable=False),
        sa.Column("serial", sa.String(128), nullable=False),
        sa.Column("lens", sa.String(128), nullable=False),
        sa.Column("created", _TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_cameras"),
        sa.UniqueConstraint("make", "model", "serial", "lens", name="uq_cameras_make_model_serial_lens"),
    )
    op.create_table(
        "campaigns",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(256), nullable=False),
        sa.Column("cron", sa.String(128), nullable=True),
        sa.Column("description", sa.Text(), nullable=True),
        sa.Column("created", _TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_campaigns"),
        sa.UniqueConstraint("name", name="uq_campaigns_name"),
    )
    op.create_table(
        "certificates",
        sa.Column("id", sa.String(64), nullable=False),
        sa.Column("camera_id", sa.Integer(), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("supersedes", sa.String(64), nullable=True),
        sa.Column("issued", _TS, nullable=False),
        sa.Column("calibration_date", sa.Date(), nullable=False),
        sa.Column("temperature_min", sa.Float(), nullable=True),
        sa.Column("temperature_max", sa.Float(), nullable=True),
        sa.Column("thermal_kind", sa.String(32), nullable=True),
        sa.Column("model_kind", sa.String(32), nullable=False),
        sa.Column("sigma0", sa.Float(), nullable=True),
        sa.Column("reprojection_rms_px", sa.Float(), nullable=True),
        sa.Column("stored", _TS, nullable=False),
        sa.Column("document", sa.JSON(), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_certificates"),
        sa.ForeignKeyConstraint(["camera_id"], ["cameras.id"], name="fk_certificates_camera_id_cameras"),
        sa.ForeignKeyConstraint(
            ["supersedes"], ["certificates.id"], name="fk_certificates_supersedes_certificates"
        ),
        sa.UniqueConstraint("camera_id", "version", name="uq_certificates_camera_id_version"),
        sa.UniqueConstraint("supersedes", name="uq_certificates_supersedes"),
        sa.CheckConstraint("version >= 1", name="ck_certificates_version_positive"),
    )
    op.create_index("ix_certificates_camera_date", "certificates", ["camera_id", "calibration_date"])
    op.create_table(
        "flights",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(256), nullable=False),
        sa.Column("date", sa.Date(), nullable=False),
        sa.Column("camera_id", sa.Integer(), nullable=False),
        sa.Column("area", sa.String(256), nullable=True),
        sa.Column("crs", sa.String(256), nullable=True),
        sa.Column("bbox_min_x", sa.Float(), nullable=True),
        sa.Column("bbox_min_y", sa.Float(), nullable=True),
        sa.Column("bbox_max_x", sa.Float(), nullable=True),
        sa.Column("bbox_max_y", sa.Float(), nullable=True),
        sa.Column("n_images", sa.Integer(), nullable=False),
        sa.Column("temperature_min", sa.Float(), nullable=True),
        sa.Column("temperature_max", sa.Float(), nullable=True),
        sa.Column("created", _TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_flights"),
        sa.ForeignKeyConstraint(["camera_id"], ["cameras.id"], name="fk_flights_camera_id_cameras"),
        sa.UniqueConstraint("name", name="uq_flights_name"),
    )
    op.create_index("ix_flights_camera_id", "flights", ["camera_id"])
    op.create_table(
        "campaign_flights",
        sa.Column("campaign_id", sa.Integer(), nullable=False),
        sa.Column("flight_id", sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint("campaign_id", "flight_id", name="pk_campaign_flights"),
        sa.ForeignKeyConstraint(
            ["campaign_id"],
            ["campaigns.id"],
            name="fk_campaign_flights_campaign_id_campaigns",
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["flight_id"], ["flights.id"], name="fk_campaign_flights_flight_id_flights", ondelete="CASCADE"
        ),
    )
    op.create_table(
        "runs",
        sa.Column("id", sa.String(64), nullable=False),
        sa.Column("kind", sa.String(64), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("configuration", sa.JSON(), nullable=False),
        sa.Column("code_version", sa.String(128), nullable=True),
        sa.Column("started", _TS, nullable=False),
        sa.Column("ended", _TS, nullable=True),
        sa.Column("timings", sa.JSON(), nullable=False),
        sa.Column("flight_id", sa.Integer(), nullable=True),
        sa.Column("campaign_id", sa.Integer(), nullable=True),
        sa.Column("certificate_id", sa.String(64), nullable=True),
        sa.Column("certificate_reason", sa.Text(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.PrimaryKeyConstraint("id", name="pk_runs"),
        sa.ForeignKeyConstraint(["flight_id"], ["flights.id"], name="fk_runs_flight_id_flights"),
        sa.ForeignKeyConstraint(["campaign_id"], ["campaigns.id"], name="fk_runs_campaign_id_campaigns"),
        sa.ForeignKeyConstraint(
            ["certificate_id"], ["certificates.id"], name="fk_runs_certificate_id_certificates"
        ),
        sa.CheckConstraint(
            "status IN ('running', 'completed', 'failed', 'cancelled')", name="ck_runs_status_known"
        ),
    )
    op.create_index("ix_runs_kind", "runs", ["kind"])
    op.create_index("ix_runs_started", "runs", ["started"])
    op.create_index("ix_runs_flight_id", "runs", ["flight_id"])
    op.create_table(
        "artifacts",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False),
        sa.Column("uri", sa.String(2048), nullable=False),
        sa.Column("kind", sa.String(64), nullable=False),
        sa.Column("schema_name", sa.String(128), nullable=True),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("producing_run_id", sa.String(64), nullable=True),
        sa.Column("created", _TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_artifacts"),
        sa.ForeignKeyConstraint(["producing_run_id"], ["runs.id"], name="fk_artifacts_producing_run_id_runs"),
        sa.UniqueConstraint("sha256", name="uq_artifacts_sha256"),
    )
    op.create_index("ix_artifacts_kind", "artifacts", ["kind"])
    op.create_index("ix_artifacts_producing_run_id", "artifacts", ["producing_run_id"])
    op.create_table(
        "run_artifacts",
        sa.Column("run_id", sa.String(64), nullable=False),
        sa.Column("artifact_id", sa.Integer(), nullable=False),
        sa.Column("role", sa.String(16), nullable=False),
        sa.PrimaryKeyConstraint("run_id", "artifact_id", "role", name="pk_run_artifacts"),
        sa.ForeignKeyConstraint(
            ["run_id"], ["runs.id"], name="fk_run_artifacts_run_id_runs", ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["artifact_id"], ["artifacts.id"], name="fk_run_artifacts_artifact_id_artifacts"
        ),
        sa.CheckConstraint("role IN ('input', 'output')", name="ck_run_artifacts_role_known"),
    )
    op.create_index("ix_run_artifacts_artifact_id", "run_artifacts", ["artifact_id"])
    op.create_table(
        "lineage_edges",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.String(64), nullable=False),
        sa.Column("input_artifact_id", sa.Integer(), nullable=False),
        sa.Column("output_artifact_id", sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_lineage_edges"),
        sa.ForeignKeyConstraint(
            ["run_id"], ["runs.id"], name="fk_lineage_edges_run_id_runs", ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["input_artifact_id"], ["artifacts.id"], name="fk_lineage_edges_input_artifact_id_artifacts"
        ),
        sa.ForeignKeyConstraint(
            ["output_artifact_id"], ["artifacts.id"], name="fk_lineage_edges_output_artifact_id_artifacts"
        ),
        sa.UniqueConstraint(
            "run_id",
            "input_artifact_id",
            "output_artifact_id",
            name="uq_lineage_edges_run_id_input_artifact_id_output_artifact_id",
        ),
    )
    op.create_index("ix_lineage_edges_input_artifact_id", "lineage_edges", ["input_artifact_id"])
    op.create_index("ix_lineage_edges_output_artifact_id", "lineage_edges", ["output_artifact_id"])

    # The database itself refuses to change or delete a stored certificate.
    dialect = op.get_bind().dialect.name
    if dialect == "sqlite":
        for event in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER certificates_no_{event.lower()} BEFORE {event} ON certificates "
                f"BEGIN SELECT RAISE(ABORT, '{_IMMUTABLE}'); END"
            )
    elif dialect == "postgresql":
        op.execute(
            "CREATE FUNCTION aerocal_certificates_immutable() RETURNS trigger LANGUAGE plpgsql AS $$ "
            f"BEGIN RAISE EXCEPTION '{_IMMUTABLE}'; END; $$"
        )
        op.execute(
            "CREATE TRIGGER certificates_immutable BEFORE UPDATE OR DELETE ON certificates "
            "FOR EACH ROW EXECUTE FUNCTION aerocal_certificates_immutable()"
        )


def downgrade() -> None:
    dialect = op.get_bind().dialect.name
    if dialect == "sqlite":
        op.execute("DROP TRIGGER IF EXISTS certificates_no_update")
        op.execute("DROP TRIGGER IF EXISTS certificates_no_delete")
    elif dialect == "postgresql":
        op.execute("DROP TRIGGER IF EXISTS certificates_immutable ON certificates")
        op.execute("DROP FUNCTION IF EXISTS aerocal_certificates_immutable()")
    for table in (
        "lineage_edges",
        "run_artifacts",
        "artifacts",
        "runs",
        "campaign_flights",
        "flights",
        "certificates",
        "campaigns",
        "cameras",
    ):
        op.drop_table(table)
