"""Bottom-layer utilities: Dr.Jit's backend and LLVM target, numpy arrays for Dr.Jit, atomic files,
plots and the finite-difference verdict."""
