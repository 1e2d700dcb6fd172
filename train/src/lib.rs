//! `train`: the Burn side (U-Net, differentiable renderer layer, streaming trainer). Arrives with the trainer issue;
//! for now it holds the CLI skeleton so the workspace and `--help` are complete.
