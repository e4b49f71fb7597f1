"""Plain-torch references of every energy term: the speed peers of the benchmarks and a second check on the kernels."""
