// Appended by the host to every module whose kernels check their loops.

// Whether this invocation's loops ran to their ends: llvmpipe ends every loop of a shader once
// 65,535 trips have run in all (shared by the shader's loops), and then this loop of `canary`
// trips (2, from a uniform, so that no compiler unrolls it) stops after its first. Called
// last; on failure the kernel sets a flag and the host composites in smaller windows or
// reports an error, never returning truncated work.
fn loops_completed(canary: u32) -> bool {
    var trips = 0u;
    for (var z = 0u; z < canary; z++) {
        trips += 1u;
    }
    return trips == canary;
}
