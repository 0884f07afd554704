"""Speed and accuracy benchmarks (run on demand with `make bench`, never by the test suite)."""
