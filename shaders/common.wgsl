// Shared declarations of the splatting kernels (docs/splatting.md). Prepended to the per-pass files.

// Camera and frame parameters, one uniform per render (see `params.rs`).
struct Params {
    rot0: vec4<f32>,    // rows of the world->camera rotation R
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    trans: vec4<f32>,   // translation t (m)
    campos: vec4<f32>,  // camera centre in the world, -R^T t (m)
    focal: vec4<f32>,   // fx, fy, cx, cy (px)
    bg: vec4<f32>,      // background RGB
    lim: vec4<f32>,     // Jacobian clamp lim_x, lim_y (tan), width, height (px)
    dims: vec4<u32>,    // width, height, tiles_x, tiles_y
    counts: vec4<u32>,  // Gaussians, SH degree, intersections, antialias (1: Mip-Splatting 2-D filter)
}

const TILE: u32 = 16u;
const NEAR: f32 = 0.01;
const LOW_PASS: f32 = 0.3; // px^2; also the variance of the 2-D Mip filter (project.rs LOW_PASS)
const ALPHA_MAX: f32 = 0.99;
const ALPHA_MIN: f32 = 0.00392156862745098; // 1/255
const T_MIN: f32 = 0.0001;

// Mip-Splatting's opacity compensation rho = sqrt(max(0, det S / det(S + LOW_PASS I))) of the 2-D
// covariance S = [[c00, c01], [c01, c11]] (px^2, before the low-pass), given det_blurred =
// det(S + LOW_PASS I) (CPU twin: `compensation` in src/splat/cpu/project.rs).
fn compensation(c00: f32, c01: f32, c11: f32, det_blurred: f32) -> f32 {
    return sqrt(max(0.0, (c00 * c11 - c01 * c01) / det_blurred));
}

// Rotation matrix of the normalised quaternion q = (w, x, y, z); WGSL matrices are column-major.
fn quat_to_mat(q: vec4<f32>) -> mat3x3<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    return mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

// World->camera rotation as a matrix (uniform rows -> column-major).
fn cam_rot(p: Params) -> mat3x3<f32> {
    return transpose(mat3x3<f32>(p.rot0.xyz, p.rot1.xyz, p.rot2.xyz));
}

// Inclusive tile rectangle (x0, y0, x1, y1) touched by mean +- radius, clamped to the grid.
fn tile_rect(m: vec2<f32>, r: f32, tiles: vec2<u32>) -> vec4<u32> {
    let lo = floor((m - vec2<f32>(r)) / f32(TILE));
    let hi = floor((m + vec2<f32>(r)) / f32(TILE));
    let mx = vec2<f32>(tiles) - vec2<f32>(1.0);
    let a = clamp(lo, vec2<f32>(0.0), mx);
    let b = clamp(hi, vec2<f32>(0.0), mx);
    return vec4<u32>(u32(a.x), u32(a.y), u32(b.x), u32(b.y));
}

const SH_C0: f32 = 0.28209479177387814;
const SH_C1: f32 = 0.4886025119029199;
const SH_C2: array<f32, 5> = array<f32, 5>(1.0925484305920792, -1.0925484305920792,
    0.31539156525252005, -1.0925484305920792, 0.5462742152960396);
const SH_C3: array<f32, 7> = array<f32, 7>(-0.5900435899266435, 2.890611442640554,
    -0.4570457994644658, 0.3731763325901154, -0.4570457994644658, 1.445305721320277,
    -0.5900435899266435);

// Real SH basis Y_0..Y_15 at the unit direction d; entries above `degree` are zero.
fn sh_basis(d: vec3<f32>, degree: u32) -> array<f32, 16> {
    var y: array<f32, 16>;
    let x = d.x;
    let yy = d.y;
    let z = d.z;
    y[0] = SH_C0;
    if degree >= 1u {
        y[1] = -SH_C1 * yy;
        y[2] = SH_C1 * z;
        y[3] = -SH_C1 * x;
    }
    if degree >= 2u {
        y[4] = SH_C2[0] * x * yy;
        y[5] = SH_C2[1] * yy * z;
        y[6] = SH_C2[2] * (2.0 * z * z - x * x - yy * yy);
        y[7] = SH_C2[3] * x * z;
        y[8] = SH_C2[4] * (x * x - yy * yy);
    }
    if degree >= 3u {
        y[9] = SH_C3[0] * yy * (3.0 * x * x - yy * yy);
        y[10] = SH_C3[1] * x * yy * z;
        y[11] = SH_C3[2] * yy * (4.0 * z * z - x * x - yy * yy);
        y[12] = SH_C3[3] * z * (2.0 * z * z - 3.0 * x * x - 3.0 * yy * yy);
        y[13] = SH_C3[4] * x * (4.0 * z * z - x * x - yy * yy);
        y[14] = SH_C3[5] * z * (x * x - yy * yy);
        y[15] = SH_C3[6] * x * (x * x - 3.0 * yy * yy);
    }
    return y;
}
