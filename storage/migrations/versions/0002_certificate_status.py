"""Certificates carry the verdict of their review: accepted or rejected.

A certificate whose calibration failed its quality gates (:mod:`aerocal.certificates.review`) is stored, so that the
failure is on record with its reasons (in the document's ``review``), but it is never selected for a
flight. Certificates stored before this revision were not reviewed and count as accepted.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # ADD COLUMN with a constant default: no table rebuild on SQLite, so the immutability triggers stay
    op.add_column(
        "certificates",
        sa.Column("status", sa.String(16), nullable=False, server_default="accepted"),
    )


def downgrade() -> None:
    with op.batch_alter_table("certificates", recreate="never") as batch:
        batch.drop_column("status")
