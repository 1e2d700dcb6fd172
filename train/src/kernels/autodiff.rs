//! [`TrainOps`] for `Autodiff<B>`: each operation is one graph node whose forward runs on the inner backend and
//! whose backward calls the inner backend's gradient kernels (so a CPU step never builds BatchNorm's ~15-node
//! broadcast graph, and the convolution's gradients come from the inner backend's own kernels).

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::autodiff::NodeId;
use burn::backend::Autodiff;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::ops::{ConvOptions, FloatTensor, IntTensor};

use super::{DropoutOutput, MaxPoolOutput, NormOutput, RenderLoss, TrainOps};

#[derive(Debug)]
struct Conv2dWithBias;
#[derive(Debug)]
struct Conv2dNoBias;
#[derive(Debug)]
struct BatchNormLeakyRelu;
#[derive(Debug)]
struct MaxPool2x2;
#[derive(Debug)]
struct DropoutMask;

impl<B: TrainOps> Backward<B, 1> for DropoutMask {
    type State = (FloatTensor<B>, f64);

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (mask, prob) = ops.state;
        let [node_x] = ops.parents;
        if let Some(node) = node_x {
            grads.register::<B>(node.id, B::dropout_backward(grad, mask, prob));
        }
    }
}

impl<B: TrainOps> Backward<B, 1> for MaxPool2x2 {
    type State = (NodeId, IntTensor<B>);

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (x, argmax) = ops.state;
        let x = checkpointer.retrieve_node_output::<FloatTensor<B>>(x);
        let [node_x] = ops.parents;
        if let Some(node) = node_x {
            grads.register::<B>(node.id, B::max_pool2x2_backward(x, grad, argmax));
        }
    }
}

/// Gradients of a convolution for whichever of input, weight and bias require one.
fn conv_backward<B: TrainOps>(
    [node_x, node_weight, node_bias]: [Option<NodeId>; 3],
    grad: FloatTensor<B>,
    (x, weight, options): (FloatTensor<B>, FloatTensor<B>, ConvOptions<2>),
    grads: &mut Gradients,
) {
    if let Some(id) = node_bias {
        grads.register::<B>(id, B::train_conv2d_bias_grad(grad.clone()));
    }
    if let Some(id) = node_weight {
        let g =
            B::train_conv2d_weight_grad(x.clone(), weight.clone(), grad.clone(), options.clone());
        grads.register::<B>(id, g);
    }
    if let Some(id) = node_x {
        grads.register::<B>(id, B::train_conv2d_x_grad(x, weight, grad, options));
    }
}

impl<B: TrainOps> Backward<B, 3> for Conv2dWithBias {
    type State = (NodeId, NodeId, ConvOptions<2>);

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (x, weight, options) = ops.state;
        let x = checkpointer.retrieve_node_output::<FloatTensor<B>>(x);
        let weight = checkpointer.retrieve_node_output::<FloatTensor<B>>(weight);
        let parents = ops.parents.map(|node| node.map(|node| node.id));
        conv_backward::<B>(parents, grad, (x, weight, options), grads);
    }
}

impl<B: TrainOps> Backward<B, 2> for Conv2dNoBias {
    type State = (NodeId, NodeId, ConvOptions<2>);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (x, weight, options) = ops.state;
        let x = checkpointer.retrieve_node_output::<FloatTensor<B>>(x);
        let weight = checkpointer.retrieve_node_output::<FloatTensor<B>>(weight);
        let [node_x, node_weight] = ops.parents.map(|node| node.map(|node| node.id));
        conv_backward::<B>(
            [node_x, node_weight, None],
            grad,
            (x, weight, options),
            grads,
        );
    }
}

#[derive(Debug)]
struct UpsampleConv2d;

impl<B: TrainOps> Backward<B, 3> for UpsampleConv2d {
    type State = (NodeId, NodeId);

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let x = checkpointer.retrieve_node_output::<FloatTensor<B>>(ops.state.0);
        let weight = checkpointer.retrieve_node_output::<FloatTensor<B>>(ops.state.1);
        let [node_x, node_weight, node_bias] = ops.parents;
        if let Some(node) = node_bias {
            grads.register::<B>(node.id, B::train_conv2d_bias_grad(grad.clone()));
        }
        if let Some(node) = node_weight {
            let g = B::train_upsample_conv2d_weight_grad(x.clone(), weight.clone(), grad.clone());
            grads.register::<B>(node.id, g);
        }
        if let Some(node) = node_x {
            grads.register::<B>(node.id, B::train_upsample_conv2d_x_grad(x, weight, grad));
        }
    }
}

#[derive(Debug)]
struct JoinChannels;

impl<B: TrainOps> Backward<B, 2> for JoinChannels {
    /// The first input (its sign sets LeakyReLU's slope) and the slope.
    type State = (NodeId, f64);

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (a, slope) = ops.state;
        let a = checkpointer.retrieve_node_output::<FloatTensor<B>>(a);
        let (grad_a, grad_b) = B::train_join_channels_backward(a, grad, slope);
        let [node_a, node_b] = ops.parents;
        for (node, value) in [(node_a, grad_a), (node_b, grad_b)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, value);
            }
        }
    }
}

#[derive(Debug)]
struct RenderMaskedMse;

impl<B: TrainOps> Backward<B, 1> for RenderMaskedMse {
    /// The raw parameters' checkpoint, the scene terms, ∂loss/∂rendered and the LeakyReLU slope.
    type State = (NodeId, FloatTensor<B>, FloatTensor<B>, f64);

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let (raw, terms, residual, slope) = ops.state;
        let raw = checkpointer.retrieve_node_output::<FloatTensor<B>>(raw);
        let [node_raw] = ops.parents;
        if let Some(node) = node_raw {
            let g = B::render_masked_mse_backward(raw, terms, residual, grad, slope);
            grads.register::<B>(node.id, g);
        }
    }
}

/// What the fused norm's backward needs besides the checkpointed input and scale.
#[derive(Debug, Clone)]
struct NormState<B: TrainOps> {
    x: NodeId,
    gamma: NodeId,
    beta: FloatTensor<B>,
    mean: FloatTensor<B>,
    var: FloatTensor<B>,
    output: FloatTensor<B>,
    epsilon: f64,
    slope: f64,
}

impl<B: TrainOps> Backward<B, 3> for BatchNormLeakyRelu {
    type State = NormState<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let s = ops.state;
        let x = checkpointer.retrieve_node_output::<FloatTensor<B>>(s.x);
        let gamma = checkpointer.retrieve_node_output::<FloatTensor<B>>(s.gamma);
        let g = B::batch_norm_leaky_relu_backward(
            x, gamma, s.beta, s.mean, s.var, s.output, grad, s.epsilon, s.slope,
        );
        let [node_x, node_gamma, node_beta] = ops.parents;
        for (node, value) in [(node_x, g.x), (node_gamma, g.gamma), (node_beta, g.beta)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, value);
            }
        }
    }
}

impl<B: TrainOps, C: CheckpointStrategy> TrainOps for Autodiff<B, C> {
    fn train_conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        match bias {
            Some(bias) => match Conv2dWithBias
                .prepare::<C>([x.node.clone(), weight.node.clone(), bias.node.clone()])
                .compute_bound()
                .stateful()
            {
                OpsKind::Tracked(mut prep) => {
                    let state = (
                        prep.checkpoint(&x),
                        prep.checkpoint(&weight),
                        options.clone(),
                    );
                    let out = B::train_conv2d(
                        x.primitive,
                        weight.primitive,
                        Some(bias.primitive),
                        options,
                    );
                    prep.finish(state, out)
                }
                OpsKind::UnTracked(prep) => prep.finish(B::train_conv2d(
                    x.primitive,
                    weight.primitive,
                    Some(bias.primitive),
                    options,
                )),
            },
            None => match Conv2dNoBias
                .prepare::<C>([x.node.clone(), weight.node.clone()])
                .compute_bound()
                .stateful()
            {
                OpsKind::Tracked(mut prep) => {
                    let state = (
                        prep.checkpoint(&x),
                        prep.checkpoint(&weight),
                        options.clone(),
                    );
                    prep.finish(
                        state,
                        B::train_conv2d(x.primitive, weight.primitive, None, options),
                    )
                }
                OpsKind::UnTracked(prep) => prep.finish(B::train_conv2d(
                    x.primitive,
                    weight.primitive,
                    None,
                    options,
                )),
            },
        }
    }

    fn dropout(x: FloatTensor<Self>, prob: f64) -> DropoutOutput<Self> {
        let prep = DropoutMask
            .prepare::<C>([x.node.clone()])
            .compute_bound()
            .stateful();
        let out = B::dropout(x.primitive, prob);
        // The mask is a constant of the step: returned without a graph node of its own.
        let mask = Self::from_inner(out.mask.clone());
        let output = match prep {
            OpsKind::Tracked(prep) => prep.finish((out.mask, prob), out.output),
            OpsKind::UnTracked(prep) => prep.finish(out.output),
        };
        DropoutOutput { output, mask }
    }

    fn max_pool2x2(x: FloatTensor<Self>) -> MaxPoolOutput<Self> {
        match MaxPool2x2
            .prepare::<C>([x.node.clone()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(mut prep) => {
                let x_id = prep.checkpoint(&x);
                let out = B::max_pool2x2(x.primitive);
                MaxPoolOutput {
                    output: prep.finish((x_id, out.argmax.clone()), out.output),
                    argmax: out.argmax,
                }
            }
            OpsKind::UnTracked(prep) => {
                let out = B::max_pool2x2(x.primitive);
                MaxPoolOutput {
                    output: prep.finish(out.output),
                    argmax: out.argmax,
                }
            }
        }
    }

    fn train_upsample_conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        // The network's up convolutions all have a bias; without one, compose the stock operations.
        let Some(bias) = bias else {
            return super::stock::upsample_conv2d::<Self>(x, weight, None);
        };
        match UpsampleConv2d
            .prepare::<C>([x.node.clone(), weight.node.clone(), bias.node.clone()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(mut prep) => {
                let state = (prep.checkpoint(&x), prep.checkpoint(&weight));
                let out =
                    B::train_upsample_conv2d(x.primitive, weight.primitive, Some(bias.primitive));
                prep.finish(state, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::train_upsample_conv2d(
                x.primitive,
                weight.primitive,
                Some(bias.primitive),
            )),
        }
    }

    fn render_masked_mse(
        raw: FloatTensor<Self>,
        terms: FloatTensor<Self>,
        image: FloatTensor<Self>,
        valid: FloatTensor<Self>,
        slope: f64,
    ) -> RenderLoss<Self> {
        // The scene (terms, image, mask) is a constant of the batch: only `raw` is a parent.
        let prep = RenderMaskedMse
            .prepare::<C>([raw.node.clone()])
            .compute_bound()
            .stateful();
        let run = |raw: FloatTensor<B>| {
            B::render_masked_mse(
                raw,
                terms.primitive.clone(),
                image.primitive,
                valid.primitive,
                slope,
            )
        };
        let (loss, residual) = match prep {
            OpsKind::Tracked(mut prep) => {
                let raw_id = prep.checkpoint(&raw);
                let out = run(raw.primitive);
                let state = (raw_id, terms.primitive, out.residual.clone(), slope);
                (prep.finish(state, out.loss), out.residual)
            }
            OpsKind::UnTracked(prep) => {
                let out = run(raw.primitive);
                (prep.finish(out.loss), out.residual)
            }
        };
        RenderLoss {
            loss,
            residual: Self::from_inner(residual),
        }
    }

    fn train_join_channels(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        slope: f64,
    ) -> FloatTensor<Self> {
        match JoinChannels
            .prepare::<C>([a.node.clone(), b.node.clone()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(mut prep) => {
                let a_id = prep.checkpoint(&a);
                prep.finish(
                    (a_id, slope),
                    B::train_join_channels(a.primitive, b.primitive, slope),
                )
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::train_join_channels(a.primitive, b.primitive, slope))
            }
        }
    }

    fn batch_norm_leaky_relu(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: f64,
        slope: f64,
    ) -> NormOutput<Self> {
        let prep = BatchNormLeakyRelu
            .prepare::<C>([x.node.clone(), gamma.node.clone(), beta.node.clone()])
            .compute_bound()
            .stateful();
        let (output, mean, var) = match prep {
            OpsKind::Tracked(mut prep) => {
                let (x_id, gamma_id) = (prep.checkpoint(&x), prep.checkpoint(&gamma));
                let out = B::batch_norm_leaky_relu(
                    x.primitive,
                    gamma.primitive,
                    beta.primitive.clone(),
                    epsilon,
                    slope,
                );
                let state = NormState {
                    x: x_id,
                    gamma: gamma_id,
                    beta: beta.primitive,
                    mean: out.mean.clone(),
                    var: out.var.clone(),
                    output: out.output.clone(),
                    epsilon,
                    slope,
                };
                (prep.finish(state, out.output), out.mean, out.var)
            }
            OpsKind::UnTracked(prep) => {
                let out = B::batch_norm_leaky_relu(
                    x.primitive,
                    gamma.primitive,
                    beta.primitive,
                    epsilon,
                    slope,
                );
                (prep.finish(out.output), out.mean, out.var)
            }
        };
        // Batch statistics feed the running ones only: no gradient flows through them.
        NormOutput {
            output,
            mean: Self::from_inner(mean),
            var: Self::from_inner(var),
        }
    }
}
