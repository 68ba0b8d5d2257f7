//! The window and the render loop: the GL side of the viewer. Everything it draws comes
//! from the pure functions of [`crate::scene`]; this module only uploads and renders.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, anyhow, bail};
use myriad_client::{ClientConfig, ClientError, Credentials, Trust};
use three_d::{
    AmbientLight, Camera, ClearState, Context, CpuMaterial, CpuMesh, DirectionalLight, Event, FrameInput, FrameOutput,
    GUI, Gm, InstancedMesh, Instances, Mesh, PhysicalMaterial, Srgba, SurfaceSettings, Window, WindowSettings, degrees,
    egui, vec3,
};

use crate::args::{Args, resolve_server};
use crate::camera::FollowCamera;
use crate::hud::{FrameTimes, HudInfo, hud_line};
use crate::net::{Login, Session, Snapshot};
use crate::reconnect::Link;
use crate::scene::{
    Batch, Batches, Part, ViewFilter, ViewObject, dynamic_batches, palette, static_batches, synthetic_objects,
    terrain_height, terrain_mesh, to_render, unit_cylinder,
};
use crate::screenshot::write_png;

/// Runs the viewer until the window closes (or `--frames` are done). Returns an error
/// for everything that can go wrong before the first frame; later failures print a
/// message and exit the process with status 1, since the window's event loop never
/// returns.
pub fn run(args: Args) -> Result<()> {
    let password =
        args.password.clone().ok_or_else(|| anyhow!("no password: set MYRIAD_PASSWORD or pass --password"))?;
    let (addr, host) = resolve_server(&args.server).map_err(|e| anyhow!(e))?;
    check_display()?;
    let trust = match &args.ca {
        Some(ca) => Trust::ca_file(ca),
        None => Trust::pin_file(&args.cert),
    }
    .map_err(|e| {
        anyhow!(
            "{e}\n(the development certificate is <data_dir>/tls-cert.pem of the server: pass --cert, or --ca for a CA)"
        )
    })?;
    if !(args.far.is_finite() && args.far > 1.0) {
        bail!("--far {}: must be more than 1 unit", args.far);
    }
    let mut config = ClientConfig::new(addr, &trust)?;
    config.server_name = host;
    config.interpolation = myriad_client::Interpolation {
        delay_ticks: args.render_delay_ticks,
        max_extrapolation: std::time::Duration::from_millis(args.max_extrapolation_ms),
    };
    eprintln!("myriad-viewer: logging in as {} at {addr}", args.user);
    let session = Session::start(config, Credentials { username: args.user.clone(), password })
        .map_err(|e| login_error(e, addr))?;
    print_login(&session.login());
    let window = open_window(&args)?;
    let mut viewer = Viewer::new(window.gl(), session, args)?;
    window.render_loop(move |frame| viewer.frame(frame));
    Ok(())
}

/// One line about a login, for the first one and every one after a session ended.
fn print_login(login: &Login) {
    let a = &login.accepted;
    let again = if login.number > 1 { " again" } else { "" };
    eprintln!(
        "myriad-viewer: logged in{again}: object {} at {:?}, map {:?} ({}×{} samples, {} static primitives), {} Hz",
        a.entity_id,
        a.position,
        a.map.name,
        login.map.terrain_width,
        login.map.terrain_depth,
        login.map.statics.len(),
        a.tick_rate_hz
    );
}

fn login_error(e: ClientError, addr: std::net::SocketAddr) -> anyhow::Error {
    match e {
        ClientError::Io { what: "connecting to the login service", source } => {
            anyhow!("cannot reach the login service at {addr}: {source} (is the server running? see --server)")
        }
        ClientError::Io { what: "TLS handshake", source } => {
            anyhow!("TLS handshake with {addr} failed: {source} (wrong --cert for this server?)")
        }
        other => anyhow!("login at {addr} failed: {other}"),
    }
}

/// winit panics when no display can be opened; say so plainly instead.
fn check_display() -> Result<()> {
    let has = |v: &str| std::env::var_os(v).is_some_and(|s| !s.is_empty());
    if cfg!(unix) && !cfg!(target_os = "macos") && !has("DISPLAY") && !has("WAYLAND_DISPLAY") {
        bail!(
            "no display: neither DISPLAY nor WAYLAND_DISPLAY is set (for a headless run, start Xvfb and set DISPLAY)"
        );
    }
    Ok(())
}

fn open_window(args: &Args) -> Result<Window> {
    let settings = WindowSettings {
        title: format!("Myriad — {}", args.user),
        initial_size: Some(args.size),
        max_size: None,
        surface_settings: SurfaceSettings {
            // Measured runs draw as fast as they can.
            vsync: args.frames.is_none(),
            multisamples: args.msaa,
            ..SurfaceSettings::default()
        },
        ..WindowSettings::default()
    };
    // winit and glutin panic on some failures (no X server behind DISPLAY, no GL):
    // turn those into an error message, without the panic's backtrace noise.
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let window = std::panic::catch_unwind(|| Window::new(settings));
    std::panic::set_hook(hook);
    match window {
        Ok(Ok(w)) => Ok(w),
        Ok(Err(e)) => Err(anyhow!("cannot open a window with OpenGL: {e:?}")),
        Err(p) => {
            let why = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            Err(anyhow!("cannot open a window on display {:?}: {why}", std::env::var("DISPLAY").unwrap_or_default()))
        }
    }
}

/// The terrain and the static scenery of a login's map.
fn map_meshes(
    context: &Context,
    material: &PhysicalMaterial,
    login: &Login,
    terrain_res: u32,
) -> Result<(Gm<Mesh, PhysicalMaterial>, PartMeshes)> {
    let mesh = terrain_mesh(&login.accepted.map, &login.map, terrain_res.max(2))
        .context("the server's heightmap cannot be drawn")?;
    let terrain = Gm::new(Mesh::new(context, &mesh), material.clone());
    let mut statics = PartMeshes::new(material.clone());
    statics.set(context, &static_batches(&login.map.statics));
    Ok((terrain, statics))
}

/// One instanced mesh per [`Part`], created on first use (an instanced mesh cannot be
/// empty) and hidden while it has no instances.
struct PartMeshes {
    cpu: [CpuMesh; 3],
    gms: [Option<Gm<InstancedMesh, PhysicalMaterial>>; 3],
    counts: [usize; 3],
    material: PhysicalMaterial,
}

const PARTS: [Part; 3] = [Part::Sphere, Part::Cube, Part::Cylinder];

impl PartMeshes {
    fn new(material: PhysicalMaterial) -> Self {
        // Modest tessellation: 10,000 objects are ~13,000 spheres with the capsule caps.
        PartMeshes {
            cpu: [CpuMesh::sphere(8), CpuMesh::cube(), unit_cylinder(12)],
            gms: [None, None, None],
            counts: [0; 3],
            material,
        }
    }

    fn set(&mut self, context: &Context, batches: &Batches) {
        for (k, part) in PARTS.into_iter().enumerate() {
            let b: &Batch = batches.part(part);
            self.counts[k] = b.len();
            if b.is_empty() {
                continue;
            }
            let instances = Instances {
                transformations: b.transforms.clone(),
                colors: Some(b.colors.clone()),
                ..Default::default()
            };
            match &mut self.gms[k] {
                Some(gm) => gm.geometry.set_instances(&instances),
                slot @ None => {
                    *slot = Some(Gm::new(InstancedMesh::new(context, &instances, &self.cpu[k]), self.material.clone()))
                }
            }
        }
    }

    fn visible(&self) -> impl Iterator<Item = &Gm<InstancedMesh, PhysicalMaterial>> {
        self.gms.iter().zip(self.counts).filter(|(_, n)| *n > 0).filter_map(|(gm, _)| gm.as_ref())
    }
}

struct Viewer {
    context: Context,
    session: Session,
    /// The login whose map is drawn and whose object is the player.
    login: Arc<Login>,
    /// The login whose player the camera was placed on.
    placed_for: u64,
    /// The link state last printed.
    printed_link: Link,
    args: Args,
    camera: Camera,
    follow: FollowCamera,
    terrain: Gm<Mesh, PhysicalMaterial>,
    statics: PartMeshes,
    dynamics: PartMeshes,
    ambient: AmbientLight,
    sun: DirectionalLight,
    gui: GUI,
    batches: Batches,
    shown_generation: u64,
    in_view: usize,
    synthetic: Vec<ViewObject>,
    merged: Vec<ViewObject>,
    started: Instant,
    first_update: Option<Instant>,
    frames_after_first: u64,
    times: FrameTimes,
    last_frame: Option<Instant>,
    /// Time spent turning snapshots into instances and uploading them (the CPU side of a
    /// world update), in milliseconds.
    update_times: FrameTimes,
}

impl Viewer {
    fn new(context: Context, session: Session, args: Args) -> Result<Self> {
        let material = PhysicalMaterial::new_opaque(
            &context,
            &CpuMaterial { albedo: Srgba::WHITE, roughness: 0.85, metallic: 0.0, ..Default::default() },
        );
        let login = session.login();
        let (terrain, statics) = map_meshes(&context, &material, &login, args.terrain_res)?;
        let (w, h) = args.size;
        let camera = Camera::new_perspective(
            three_d::Viewport::new_at_origo(w, h),
            vec3(0.0, 10.0, -10.0),
            vec3(0.0, 0.0, 0.0),
            vec3(0.0, 1.0, 0.0),
            degrees(60.0),
            0.1,
            args.far,
        );
        Ok(Viewer {
            ambient: AmbientLight::new(&context, 0.45, Srgba::WHITE),
            // From behind the camera's usual side, high up: the faces the player sees are lit.
            sun: DirectionalLight::new(&context, 2.2, Srgba::WHITE, vec3(-0.35, -1.0, 0.55)),
            gui: GUI::new(&context),
            dynamics: PartMeshes::new(material),
            statics,
            terrain,
            camera,
            follow: FollowCamera::default(),
            batches: Batches::default(),
            shown_generation: 0,
            in_view: 0,
            synthetic: Vec::new(),
            merged: Vec::new(),
            started: Instant::now(),
            first_update: None,
            frames_after_first: 0,
            times: FrameTimes::default(),
            last_frame: None,
            update_times: FrameTimes::default(),
            placed_for: 0,
            printed_link: Link::LoggingIn,
            context,
            session,
            login,
            args,
        })
    }

    fn ground(&self) -> impl Fn(f32, f32) -> f32 + '_ {
        |x, z| terrain_height(&self.login.accepted.map, &self.login.map, x, z)
    }

    /// Takes the newest login after a session ended and a new one began: the player's
    /// object may have another id, and a restarted server may serve another map.
    fn follow_login(&mut self) {
        let login = self.session.login();
        if login.number == self.login.number {
            return;
        }
        print_login(&login);
        if login.accepted.map != self.login.accepted.map || login.map != self.login.map {
            let material = self.terrain.material.clone();
            match map_meshes(&self.context, &material, &login, self.args.terrain_res) {
                Ok((terrain, statics)) => (self.terrain, self.statics) = (terrain, statics),
                Err(e) => self.exit(1, &format!("{e:#}")),
            }
        }
        self.login = login;
    }

    /// Says on stderr what the status line says about the link, once per change.
    fn print_link(&mut self, link: &Link) {
        if *link != self.printed_link {
            eprintln!("myriad-viewer: {}", link.status(Instant::now()));
            self.printed_link = link.clone();
        }
    }

    fn frame(&mut self, mut frame: FrameInput) -> FrameOutput {
        let now = Instant::now();
        if let Some(prev) = self.last_frame.replace(now) {
            self.times.record(now.duration_since(prev).as_secs_f64() * 1000.0);
        }
        for event in &frame.events {
            match event {
                Event::KeyPress { kind, .. } => {
                    self.session.shared.with_keys(|k| k.handle(*kind, true));
                }
                Event::KeyRelease { kind, .. } => {
                    self.session.shared.with_keys(|k| k.handle(*kind, false));
                }
                _ => {}
            }
        }
        let snap = self.session.shared.snapshot();
        if snap.login != self.login.number {
            self.follow_login();
        }
        self.print_link(&snap.link);
        let player = snap.own_position.unwrap_or(self.login.accepted.position);
        let (desc, map) = (&self.login.accepted.map, &self.login.map);
        let dt = frame.elapsed_time as f32 / 1000.0;
        let (eye, target) = self.follow.update(player, dt, |x, z| terrain_height(desc, map, x, z));
        self.camera.set_viewport(frame.viewport);
        self.camera.set_view(to_render(eye), to_render(target), vec3(0.0, 1.0, 0.0));
        if snap.generation != self.shown_generation {
            let t = Instant::now();
            self.show(&snap, eye);
            self.update_times.record(t.elapsed().as_secs_f64() * 1000.0);
        }
        if let Link::Disconnected { reason } = &snap.link
            && self.first_update.is_none()
        {
            self.exit(1, &format!("no world update before the session ended: {reason}"));
        }

        let line = hud_line(&HudInfo {
            tick: snap.tick,
            in_view: self.in_view,
            ping: snap.ping,
            bytes_per_s: snap.bytes_per_s,
            dilation_permille: snap.dilation_permille,
            fps: self.times.fps(),
        });
        let link = snap.link.status(now);
        let link_colour = if snap.link.is_connected() { egui::Color32::LIGHT_GREEN } else { egui::Color32::LIGHT_RED };
        self.gui.update(&mut frame.events, frame.accumulated_time, frame.viewport, frame.device_pixel_ratio, |ui| {
            egui::Frame::new().fill(egui::Color32::from_black_alpha(170)).inner_margin(8).show(ui, |ui| {
                ui.label(egui::RichText::new(&line).monospace().size(18.0).color(egui::Color32::WHITE));
                ui.label(egui::RichText::new(&link).monospace().size(16.0).color(link_colour));
            });
        });

        let sky = palette::SKY;
        let lights: [&dyn three_d::Light; 2] = [&self.ambient, &self.sun];
        let objects = std::iter::once(&self.terrain as &dyn three_d::Object)
            .chain(self.statics.visible().map(|g| g as &dyn three_d::Object))
            .chain(self.dynamics.visible().map(|g| g as &dyn three_d::Object));
        let screen = frame.screen();
        screen
            .clear(ClearState::color_and_depth(
                sky.r as f32 / 255.0,
                sky.g as f32 / 255.0,
                sky.b as f32 / 255.0,
                1.0,
                1.0,
            ))
            .render(&self.camera, objects, &lights)
            .write(|| self.gui.render())
            .ok();

        if let Some(first) = self.first_update {
            self.frames_after_first += 1;
            if let Some(n) = self.args.frames
                && self.frames_after_first >= n
            {
                if let Some(path) = &self.args.screenshot {
                    let pixels = screen.read_color::<[u8; 4]>();
                    let (w, h) = (frame.viewport.width, frame.viewport.height);
                    if let Err(e) = write_png(path, w, h, &pixels) {
                        self.exit(1, &format!("cannot save the screenshot: {e}"));
                    }
                    eprintln!("myriad-viewer: screenshot {} ({w}×{h})", path.display());
                }
                self.report(first.elapsed());
                self.exit(0, "");
            }
        } else if self.args.frames.is_some() && self.started.elapsed() > Duration::from_secs_f64(self.args.wait) {
            self.exit(1, &format!("no world update within {} s", self.args.wait));
        }
        FrameOutput::default()
    }

    /// Rebuilds the dynamic instances from a new snapshot.
    fn show(&mut self, snap: &Arc<Snapshot>, eye: [f32; 3]) {
        self.shown_generation = snap.generation;
        let Some(own) = snap.own_position else { return };
        if self.placed_for != snap.login {
            // The camera jumps to the player's real position once known, and again after
            // a new login (the player may be elsewhere now).
            self.follow = FollowCamera::default();
            self.placed_for = snap.login;
        }
        if self.first_update.is_none() {
            self.first_update = Some(Instant::now());
            if self.args.bench_objects > 0 {
                self.synthetic = synthetic_objects(self.args.bench_objects, own, 1.5, self.ground());
            }
        }
        let filter = ViewFilter {
            own_id: self.login.accepted.entity_id,
            own_shape: self.login.accepted.shape,
            eye,
            far: self.args.far,
        };
        let objects: &[ViewObject] = if self.synthetic.is_empty() {
            &snap.objects
        } else {
            self.merged.clear();
            self.merged.extend_from_slice(&snap.objects);
            self.merged.extend_from_slice(&self.synthetic);
            &self.merged
        };
        self.in_view = dynamic_batches(objects, &filter, &mut self.batches);
        self.dynamics.set(&self.context, &self.batches);
    }

    fn report(&self, since_first: Duration) {
        // The first frames compile shaders and upload buffers: leave them out.
        let skip = (self.times.samples_ms.len() / 10).min(10);
        if let Some((mean, p50, p95)) = self.times.summary(skip) {
            let updates = self.update_times.summary(1).map_or_else(String::new, |(m, _, p)| {
                format!(
                    " | {} world updates, instance rebuild + upload mean {m:.2} ms, p95 {p:.2} ms",
                    self.update_times.samples_ms.len()
                )
            });
            println!(
                "frames {} | objects in view {} | instances {} | frame time mean {mean:.2} ms, median {p50:.2} ms, p95 {p95:.2} ms ({:.1} fps){updates} | {:.1} s since the first update",
                self.times.samples_ms.len() - skip,
                self.in_view,
                self.batches.total(),
                1000.0 / mean,
                since_first.as_secs_f64(),
            );
        }
    }

    /// Leaves: the window's event loop cannot return a status, so exit from here.
    fn exit(&mut self, code: i32, message: &str) -> ! {
        if !message.is_empty() {
            eprintln!("myriad-viewer: {message}");
        }
        self.session.stop(Duration::from_millis(500));
        std::process::exit(code);
    }
}
