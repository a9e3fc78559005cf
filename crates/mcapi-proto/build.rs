//! Compiles the workspace's `proto/` (kept at the repository's top level,
//! beside the clients that also generate from it) into Rust (prost messages,
//! tonic client and server) in `OUT_DIR`, with `protox` as a pure-Rust
//! protobuf compiler: no system `protoc` is needed. The encoded descriptor
//! set goes to `OUT_DIR` too, for the reflection service.

use std::env;
use std::fs;
use std::path::PathBuf;

const PROTOS: [&str; 1] = ["mcapi/v1/agents.proto"];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // crates/mcapi-proto -> the workspace root's proto/.
    let root = PathBuf::from(env::var("CARGO_MANIFEST_DIR")?).join("../../proto");
    println!("cargo:rerun-if-changed={}", root.display());
    let out_dir = PathBuf::from(env::var("OUT_DIR")?);

    let mut compiler = protox::Compiler::new([&root])?;
    compiler.include_source_info(true).include_imports(true);
    compiler.open_files(PROTOS)?;
    fs::write(
        out_dir.join("mcapi_descriptor.bin"),
        compiler.encode_file_descriptor_set(),
    )?;

    tonic_prost_build::configure()
        .out_dir(&out_dir)
        .compile_fds(compiler.file_descriptor_set())?;
    Ok(())
}
