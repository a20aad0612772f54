"""Reference implementations the optimised code is checked against: `gsplat` runs gsplat's own
torch rasterizer on the CPU. Used by the tests and `bench` only; nothing in the library
imports it (an import contract in `make lint` enforces that)."""
