use clap::Parser;

fn main() -> std::process::ExitCode {
    let cli = homing_datasets::cli::Cli::parse();
    match homing_datasets::cli::run(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
