"""Runs record which process runs them, so that a run whose process died is not shown as running for ever.

``runs.runner`` is ``"host:pid:start"`` (the host name, the process id and the process's start time in
clock ticks since boot, which tells a reused pid from the original process). A run still marked running
whose runner is on this host and no longer alive is recorded as failed the next time runs are listed
(:func:`storage.runs.reap_dead_runs`). Runs recorded before this revision have no runner and are left
as they are.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-25
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("runs", sa.Column("runner", sa.String(128), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("runner")
