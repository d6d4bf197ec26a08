"""What keeps a fusion map across crashes and restarts: the write-ahead journal, the reorder
buffer that puts the tracker's messages back in order, snapshots and replay."""
