"""The generator of synthetic captures with known answers (paintings, spheres, element maps), for
tests, benchmarks and ``uvps demo``. The numeric library never imports it."""
