//! `g2r-xtask`: the repository's developer tasks, kept out of the trainer (the `xtask` habit of cargo and
//! rust-analyzer). `cargo run -p g2r-xtask -- results-page [--check]`.

mod results_page;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "g2r-xtask",
    version,
    about = "Developer tasks of the g2r repository"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Write docs/results.md (what stands) and docs/results-archive.md (what no longer does) from the JSON result
    /// records in docs/results/ (one file per section, in file-name order), and refill the README's generated
    /// tables from them; with --check, write nothing and fail when a page or a generated table differs from what
    /// the records give. Either page over 40 KiB or with a line over 200 characters is an error.
    ResultsPage {
        /// Directory of result records (`NN-name.json`).
        #[arg(long, default_value = "docs/results")]
        records: PathBuf,
        /// The page of figures that stand, written (or, with --check, compared).
        #[arg(long, default_value = "docs/results.md")]
        out: PathBuf,
        /// The page of archived figures (a record's or a row's `archived`), written (or compared).
        #[arg(long, default_value = "docs/results-archive.md")]
        archive_out: PathBuf,
        /// Documents whose generated blocks (`<!-- generated: results-page NN-name.json -->` … `<!-- end
        /// generated -->`) hold a record's table, refilled (or, with --check, compared) too.
        #[arg(long = "embed-in", default_value = "README.md")]
        embed_in: Vec<PathBuf>,
        /// Compare instead of writing: exit non-zero when a page is not exactly the generated one.
        #[arg(long)]
        check: bool,
    },
}

fn main() {
    dataset::init_logging();
    if let Err(e) = run(Cli::parse()) {
        eprintln!("{}", dataset::error_line(&e));
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::ResultsPage {
            records,
            out,
            archive_out,
            embed_in,
            check,
        } => {
            let paths = results_page::PagePaths {
                records: &records,
                current: &out,
                archive: &archive_out,
            };
            dataset::outln!("{}", results_page::run_job(&paths, &embed_in, check)?);
        }
    }
    Ok(())
}
