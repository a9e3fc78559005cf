//! The core knows nothing of the network (STYLE.md, habit 1): `src/algo`
//! must not mention the server's frameworks.

use std::fs;
use std::path::Path;

const FORBIDDEN: [&str; 6] = ["tokio", "axum", "tonic", "prost", "tower", "hyper"];

fn rust_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    for entry in fs::read_dir(dir).expect("readable source dir") {
        let path = entry.expect("dir entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn algo_core_does_not_mention_network_crates() {
    let mut files = Vec::new();
    rust_files(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("src/algo"),
        &mut files,
    );
    assert!(files.len() >= 8, "found only {files:?}");
    for file in files {
        let text = fs::read_to_string(&file).expect("readable file");
        for word in FORBIDDEN {
            assert!(
                !text.contains(word),
                "{} mentions `{word}`: the core must stay free of I/O and async",
                file.display()
            );
        }
    }
}
