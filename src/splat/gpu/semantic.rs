//! L_geo on the GPU (`shaders/semantic.wgsl`): the anchors sit in two uniform grids (trunk and
//! leaf) uploaded once — anchors do not move during training, only the Gaussians do, so every
//! step searches the grids afresh from the current means. Three passes per step, recorded after
//! the photometric backward pass and before Adam: query (neighbours, weights, targets), reduce
//! (W and L_geo, which lands in the fourth float of the loss read-back) and apply (adds
//! gamma × the gradient to the mean and log-scale gradients). The CPU twin is
//! [`crate::splat::semantic`]. The same anchors serve Sylva's binding: one pass after Adam
//! ([`GpuSemantic::encode_bind`]) whose CPU twin is [`crate::splat::bind::project`].

use crate::splat::bind::BindConfig;
use crate::splat::gpu::buffers::{
    params_from, pipeline, read_buffer, storage_from, storage_zeroed, wgsl_struct,
};
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::project::{dispatch, groups_for};
use crate::splat::gpu::splats::{GpuGrads, GpuSplats};
use crate::splat::semantic::{AnchorGrid, SemanticAnchors, SemanticConfig};

const SOURCE: &str = include_str!("../../../shaders/semantic.wgsl");

/// How far past the nearest trunk anchor the leaf search goes, in temperatures: beyond 30 T
/// the trunk score q = sigmoid((d_l − d_t)/T) is 1 to f32 precision.
const LEAF_CUTOFF_TEMPERATURES: f32 = 30.0;

/// The text of one pass: the uniform [`GeoParams`], everything before the first `#ifdef`, then
/// the blocks `names` in order (e.g. `["GRID", "QUERY"]`).
pub fn pass_source(names: &[&str]) -> Result<String, GpuError> {
    // Directives stand at the start of a line (comments may mention them).
    let mut text = GeoParams::wgsl();
    text.push_str(SOURCE.split("\n#ifdef ").next().unwrap_or_default());
    for name in names {
        let marker = format!("\n#ifdef {name}\n");
        let start = SOURCE
            .find(&marker)
            .ok_or_else(|| GpuError::Invalid(format!("semantic.wgsl has no {name} block")))?
            + marker.len();
        let len = SOURCE[start..]
            .find("\n#endif")
            .ok_or_else(|| GpuError::Invalid(format!("semantic.wgsl: {name} block not closed")))?;
        text.push('\n');
        text.push_str(&SOURCE[start..start + len]);
    }
    Ok(text)
}

wgsl_struct! {
    /// The parameter buffer of every pass of `semantic.wgsl`.
    struct GeoParams {
        n: u32,
        k: u32,
        /// Index of the leaf grid's first cell in `starts`.
        leaf_cell_base: u32,
        n_leaf: u32,
        t_origin: [f32; 3],
        t_cell: f32,
        t_dims: [u32; 3],
        _p0: u32,
        l_origin: [f32; 3],
        l_cell: f32,
        l_dims: [u32; 3],
        _p1: u32,
        temperature: f32,
        beta: f32,
        eps: f32,
        threshold: f32,
        inv_npos2: f32,
        gamma: f32,
        /// The leaf search stops once rings reach d_t + this (q saturates).
        leaf_cutoff: f32,
        _p2: f32,
        /// Largest |offset| along the normal, metres.
        bind_band: f32,
        /// Cap of the z log-scale.
        bind_log_scale: f32,
        /// Gaussians with P at or above this are bound.
        bind_min_prob: f32,
        _p3: f32,
    }
}

/// The anchors, their grids and the per-model scratch of L_geo on the GPU.
pub struct GpuSemantic {
    query: wgpu::ComputePipeline,
    reduce: wgpu::ComputePipeline,
    apply: wgpu::ComputePipeline,
    bind: wgpu::ComputePipeline,
    starts: wgpu::Buffer,
    anchors: wgpu::Buffer,
    /// Unit normals of the trunk anchors in the trunk grid's order (zero where unknown).
    normals: wgpu::Buffer,
    params: GeoParams,
    /// The installed model's buffers, for `count` Gaussians.
    model: Option<ModelBuffers>,
    count: u32,
    /// (W, Σ w·term, L_geo, 0) of the latest step.
    sums: wgpu::Buffer,
}

/// The buffers of an installed model: trunk probabilities and the 2 vec4 per Gaussian of the
/// query.
struct ModelBuffers {
    trunk_prob: wgpu::Buffer,
    geo: wgpu::Buffer,
}

impl GpuSemantic {
    /// Builds the grids over `anchors` and uploads them.
    pub fn new(
        ctx: &GpuContext,
        anchors: &SemanticAnchors,
        cfg: &SemanticConfig,
    ) -> Result<Self, GpuError> {
        cfg.validate().map_err(GpuError::Invalid)?;
        let trunk = AnchorGrid::build(&anchors.trunk);
        let leaf = AnchorGrid::build(&anchors.leaf);
        let mut starts = trunk.cell_start.clone();
        let leaf_cell_base = starts.len() as u32;
        starts.extend_from_slice(&leaf.cell_start);
        let points: Vec<[f32; 4]> = trunk
            .points
            .iter()
            .chain(&leaf.points)
            .map(|p| [p[0], p[1], p[2], 0.0])
            .collect();
        let params = GeoParams {
            n: 0,
            k: cfg.k.min(trunk.points.len() as u32).max(1),
            leaf_cell_base,
            n_leaf: leaf.points.len() as u32,
            t_origin: trunk.origin,
            t_cell: trunk.cell,
            t_dims: trunk.dims,
            _p0: 0,
            l_origin: leaf.origin,
            l_cell: leaf.cell,
            l_dims: leaf.dims,
            _p1: 0,
            temperature: cfg.temperature_m,
            beta: cfg.beta,
            eps: cfg.eps_m,
            threshold: cfg.weight_threshold,
            inv_npos2: 1.0 / (anchors.n_pos * anchors.n_pos),
            gamma: 0.0,
            leaf_cutoff: LEAF_CUTOFF_TEMPERATURES * cfg.temperature_m,
            _p2: 0.0,
            bind_band: 0.0,
            bind_log_scale: 0.0,
            bind_min_prob: f32::INFINITY,
            _p3: 0.0,
        };
        let normals: Vec<[f32; 4]> = trunk
            .order
            .iter()
            .map(|&i| {
                let n = anchors
                    .trunk_normals
                    .get(i as usize)
                    .copied()
                    .unwrap_or([0.0; 3]);
                [n[0], n[1], n[2], 0.0]
            })
            .collect();
        // wgpu refuses empty buffers: one zero normal stands for none.
        let normals = if normals.is_empty() {
            vec![[0.0f32; 4]]
        } else {
            normals
        };
        Ok(GpuSemantic {
            query: pipeline(
                ctx,
                "semantic query",
                &pass_source(&["GRID", "QUERY"])?,
                "query",
            ),
            reduce: pipeline(ctx, "semantic reduce", &pass_source(&["REDUCE"])?, "reduce"),
            apply: pipeline(ctx, "semantic apply", &pass_source(&["APPLY"])?, "apply"),
            bind: pipeline(
                ctx,
                "trunk binding",
                &pass_source(&["GRID", "BIND"])?,
                "bind",
            ),
            starts: storage_from(ctx, "semantic cell starts", &starts)?,
            anchors: storage_from(ctx, "semantic anchors", &points)?,
            normals: storage_from(ctx, "trunk anchor normals", &normals)?,
            params,
            model: None,
            count: 0,
            sums: storage_zeroed(ctx, "semantic sums", 16)?,
        })
    }

    /// Installs the trunk probabilities of a (new or refined) model.
    pub fn set_model(&mut self, ctx: &GpuContext, trunk_prob: &[f32]) -> Result<(), GpuError> {
        let n = trunk_prob.len() as u32;
        self.model = Some(ModelBuffers {
            trunk_prob: storage_from(ctx, "trunk prob", trunk_prob)?,
            geo: storage_zeroed(ctx, "semantic targets", n as u64 * 32)?,
        });
        self.count = n;
        Ok(())
    }

    /// Records the three passes: L_geo's gradient × `gamma` is added to `grads`, L_geo itself
    /// is written to `loss_out[3]` (16-byte loss read-back buffer).
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
        grads: &GpuGrads,
        loss_out: &wgpu::Buffer,
        gamma: f32,
    ) -> Result<(), GpuError> {
        let model = self.installed(ctx, "semantic term", &[splats.count, grads.count])?;
        let (prob, geo) = (&model.trunk_prob, &model.geo);
        let params = GeoParams {
            n: self.count,
            gamma,
            ..self.params
        };
        let u = params_from(ctx, "semantic params", &params);
        let groups = groups_for(self.count);
        dispatch(
            ctx,
            enc,
            &self.query,
            &[
                &u,
                &splats.means,
                &splats.opacity_logits,
                prob,
                &self.starts,
                &self.anchors,
                geo,
            ],
            groups,
        );
        dispatch(
            ctx,
            enc,
            &self.reduce,
            &[
                &u,
                &splats.log_scales,
                geo,
                &self.sums,
                &splats.means,
                loss_out,
            ],
            (1, 1),
        );
        dispatch(
            ctx,
            enc,
            &self.apply,
            &[
                &u,
                &splats.means,
                &splats.log_scales,
                geo,
                &self.sums,
                &grads.means,
                &grads.log_scales,
            ],
            groups,
        );
        Ok(())
    }

    /// Installs the binding's settings (see [`crate::splat::bind`]); the CPU twin is
    /// [`crate::splat::bind::project`].
    pub fn set_bind(&mut self, cfg: &BindConfig) -> Result<(), GpuError> {
        cfg.validate().map_err(GpuError::Invalid)?;
        self.params.bind_band = cfg.band_m;
        self.params.bind_log_scale = cfg.normal_scale_m.ln();
        self.params.bind_min_prob = cfg.min_trunk_prob;
        Ok(())
    }

    /// Records the binding's projection of every bound Gaussian (after the optimiser step).
    pub fn encode_bind(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
    ) -> Result<(), GpuError> {
        let prob = &self
            .installed(ctx, "trunk binding", &[splats.count])?
            .trunk_prob;
        ctx.check_binding(
            "rotations (bound whole by the trunk binding)",
            self.count as u64 * 16,
        )?;
        let params = GeoParams {
            n: self.count,
            k: 1,
            ..self.params
        };
        let u = params_from(ctx, "binding params", &params);
        dispatch(
            ctx,
            enc,
            &self.bind,
            &[
                &u,
                &splats.means,
                &splats.log_scales,
                prob,
                &self.starts,
                &self.anchors,
                &splats.rotations,
                &self.normals,
            ],
            groups_for(self.count),
        );
        Ok(())
    }

    /// The installed model's buffers; `what` names the caller in the error.
    fn model(&self, what: &str) -> Result<&ModelBuffers, GpuError> {
        self.model
            .as_ref()
            .ok_or_else(|| GpuError::Invalid(format!("{what}: no model installed")))
    }

    /// [`GpuSemantic::model`], once checked for the pass `what` (named in the errors): each of
    /// `counts` (the model's, the gradients') is the installed model's Gaussian count, and its
    /// means and log-scales (12 bytes per Gaussian) fit one binding: the reduction reads every
    /// Gaussian in one workgroup, so the passes bind them whole rather than in chunks.
    fn installed(
        &self,
        ctx: &GpuContext,
        what: &str,
        counts: &[u32],
    ) -> Result<&ModelBuffers, GpuError> {
        let model = self.model(what)?;
        if let Some(c) = counts.iter().find(|&&c| c != self.count) {
            return Err(GpuError::Invalid(format!(
                "{what} for {} Gaussians, given a buffer of {c}",
                self.count
            )));
        }
        ctx.check_binding(
            "means and log-scales (bound whole by the semantic passes)",
            self.count as u64 * 12,
        )?;
        Ok(model)
    }

    /// Reads the latest query back (blocking; for tests): per Gaussian (a_nn xyz, s_target,
    /// w, 0, 0, 0), and (W, Σ w·term, L_geo, 0).
    pub fn read_back(&self, ctx: &GpuContext) -> Result<(Vec<[f32; 8]>, [f32; 4]), GpuError> {
        let model = self.model("semantic read-back")?;
        let flat: Vec<f32> = read_buffer(ctx, &model.geo, self.count as usize * 8)?;
        let rows = flat
            .chunks_exact(8)
            .map(|c| std::array::from_fn(|j| c[j]))
            .collect();
        let s: Vec<f32> = read_buffer(ctx, &self.sums, 4)?;
        Ok((
            rows,
            std::array::from_fn(|j| s.get(j).copied().unwrap_or(0.0)),
        ))
    }
}
