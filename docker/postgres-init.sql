-- Run once by the postgres image on an empty data volume: a database for Prefect's own records beside
-- aerocal's (POSTGRES_DB), both owned by POSTGRES_USER.
CREATE DATABASE prefect OWNER aerocal;
