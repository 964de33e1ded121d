"""Pure motion-capture algorithms on numpy arrays: no Zenoh, no files, no processes."""
