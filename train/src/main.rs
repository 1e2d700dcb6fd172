//! `g2r-train`: learn a spatially varying lunar BRDF from DEM geometry (Burn).

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "g2r-train",
    version,
    about = "Train and evaluate a U-Net that maps 128x128 DEM crops to per-pixel BRDF parameters (M1-M6)",
    long_about = "Train and evaluate a U-Net that maps 128x128 DEM crops (5 m/px) to per-pixel parameters of a small \
cosine-polynomial BRDF, supervised by rendering through a differentiable renderer layer and comparing with the real \
orthoimage (MSE over valid, lit pixels).\n\nThe trainer, evaluation and rendering commands arrive with the trainer \
issue; this build lists the BRDF models the data contract defines."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// List the BRDF models M1-M6 with their parameter order (the band order of parameter GeoTIFFs).
    Models,
}

fn main() {
    match Cli::parse().command {
        Command::Models => {
            for model in dataset::brdf::BrdfModel::ALL {
                println!(
                    "{}: {} params: {}",
                    model.name(),
                    model.param_count(),
                    model.term_names().join(", ")
                );
            }
        }
    }
}
