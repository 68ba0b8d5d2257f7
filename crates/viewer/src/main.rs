//! `myriad-viewer`: see the library's documentation.

use clap::Parser;

fn main() -> std::process::ExitCode {
    let args = myriad_viewer::Args::parse();
    match myriad_viewer::run(args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("myriad-viewer: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
