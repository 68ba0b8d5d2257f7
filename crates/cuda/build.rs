//! Compiles the replica kernels' shared logic for the host (`src/replica/host.c`), for
//! the test that holds it to the Rust replica on machines without a GPU.

fn main() {
    println!("cargo:rerun-if-changed=src/replica/host.c");
    println!("cargo:rerun-if-changed=kernels/replica.cuh");
    println!("cargo:rerun-if-changed=kernels/pack.cuh");
    cc::Build::new()
        .file("src/replica/host.c")
        .flag_if_supported("-ffp-contract=off")
        .flag_if_supported("-fno-fast-math")
        .flag_if_supported("-std=c11")
        .warnings(true)
        .compile("myriad_replica_host");
}
