use crate::common;

#[test]
fn context_reports_adapter() {
    let Some(ctx) = common::context() else { return };
    eprintln!(
        "{} atomic={:?} max_binding={} features={:?}",
        ctx.description,
        ctx.atomic_mode,
        ctx.max_binding_bytes,
        ctx.adapter.features()
    );
    assert!(ctx.max_binding_bytes >= 128 << 20);
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    use sylva::splat::gpu::{GpuSplats, Renderer};
    let Some(ctx) = common::context() else { return };
    let mut model = common::scene(1, 10, 0, 1.0);
    model.sh.pop();
    assert!(GpuSplats::upload(&ctx, &model).is_err());
    let model = common::scene(1, 10, 0, 1.0);
    let splats = GpuSplats::upload(&ctx, &model).expect("upload");
    let renderer = Renderer::new(&ctx);
    let cam = common::camera(0, 16, 10.0);
    assert!(renderer.render(&ctx, &splats, &cam, [0.0; 3]).is_err());
    let err = ctx.check_binding("test", u64::MAX).expect_err("too large");
    assert!(err.to_string().contains("storage binding"));
    // An empty model renders the background.
    let empty = GpuSplats::upload(&ctx, &Default::default()).expect("upload");
    let cam = common::camera(20, 18, 16.0);
    let frame = renderer
        .render(&ctx, &empty, &cam, [0.25; 3])
        .expect("render");
    let img = frame.read_image(&ctx).expect("read");
    assert!(img.iter().flatten().all(|&v| v == 0.25));
}
