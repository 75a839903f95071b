"""The human tasks: task and label files, their ingest and import, the stages that wait for people."""
