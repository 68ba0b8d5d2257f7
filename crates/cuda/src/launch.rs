//! Typed kernel launches: one argument struct per kernel, with named, typed fields.
//!
//! # How it works
//! A raw driver launch takes a list of untyped argument slots, so a swapped or missing
//! argument would only show as wrong physics on the device. Here instead:
//!
//! - device addresses are [`DevPtr<T>`], typed by the item they point to (`f32`, `u32`,
//!   `u64`, `u8`, `u16`, the tree's [`Node`] or the [`DeviceParams`] block), and every
//!   device buffer ([`crate::device::DevBuf<T>`]) hands out pointers of its own item type;
//! - each kernel has a struct below (`KBoxes` for `k_boxes`, …) whose fields are the
//!   kernel's parameters, **in the kernel's order and under the kernel's names**; a call
//!   site fills the fields by name, so passing `shape` where `pos` is expected does not
//!   compile, and two arguments of the same type cannot trade places silently either;
//! - [`Gpu::launch`] and [`Gpu::launch_grid`] take any [`Kernel`] and turn its fields
//!   into the driver's slots in declaration order.
//!
//! The unit test at the end reads the `extern "C" __global__` signatures from the
//! kernel sources and checks, for every kernel, that the struct's fields have the
//! parameters' names, in order, with matching C types (pointer or value, item type), so
//! the structs cannot drift from the C++ side either.

use std::marker::PhantomData;

use cudarc::driver::sys::CUdeviceptr;
use myriad_physics::PhysicsError;

use crate::device::{Arg, Gpu};
use crate::params::DeviceParams;
use crate::replica::{
    RCand, RChosen, RCommit, RConfig, RDue, RFlight, RHome, RInfo, RKey, RMoved, RObj, RPacked, RPlayer, RState, RTrack,
};

/// A device address of items of type `T` (no ownership: the buffer it came from owns the
/// memory). The null pointer stands for an absent optional array (e.g. no query order).
pub(crate) struct DevPtr<T> {
    raw: CUdeviceptr,
    // `fn() -> T`: the pointer neither owns a `T` nor stops the value being `Send`.
    _item: PhantomData<fn() -> T>,
}

// Derives would require `T: Clone`; a device address is copyable whatever it points to.
impl<T> Clone for DevPtr<T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for DevPtr<T> {}

impl<T> DevPtr<T> {
    /// The null pointer, for the kernels' optional arrays.
    pub const NULL: DevPtr<T> = DevPtr { raw: 0, _item: PhantomData };

    /// Wraps a raw address that holds items of `T`.
    pub(crate) fn from_raw(raw: CUdeviceptr) -> DevPtr<T> {
        DevPtr { raw, _item: PhantomData }
    }

    /// The raw address, for the driver.
    pub(crate) fn raw(self) -> CUdeviceptr {
        self.raw
    }

    /// The address `items` items further on (pointer arithmetic in units of `T`).
    pub(crate) fn add(self, items: usize) -> DevPtr<T> {
        DevPtr::from_raw(self.raw + (items * std::mem::size_of::<T>()) as CUdeviceptr)
    }
}

/// The kernels' internal tree node (`struct Node` in `kernels/lbvh.cu`): two child boxes
/// and two child indices, 64 bytes. The host never reads nodes; the type exists so that
/// node buffers get pointers of their own type and their size in bytes is known.
#[allow(dead_code)] // Never built on the host: only its size and its name are used.
#[repr(C, align(64))]
pub(crate) struct Node {
    b: [f32; 12],
    child: [u32; 2],
    pad: [u32; 2],
}

const _: () = assert!(std::mem::size_of::<Node>() == 64);

/// The C name of an item type a device pointer can point to.
pub(crate) trait DeviceItem {
    /// The type's name in the kernel sources.
    #[allow(dead_code)] // Read only by the signature test.
    const C_TYPE: &'static str;
}

/// `impl DeviceItem` for each Rust type with its C name.
macro_rules! device_items {
    ($($t:ty => $c:literal),* $(,)?) => {
        $(impl DeviceItem for $t {
            const C_TYPE: &'static str = $c;
        })*
    };
}

device_items!(
    f32 => "float",
    u32 => "u32",
    u64 => "u64",
    u8 => "u8",
    u16 => "unsigned short",
    Node => "Node",
    DeviceParams => "Params",
    RTrack => "RTrack",
    RObj => "RObj",
    RConfig => "RConfig",
    RCand => "RCand",
    RFlight => "RFlight",
    RState => "RState",
    RMoved => "RMoved",
    RDue => "RDue",
    RChosen => "RChosen",
    RHome => "RHome",
    RPlayer => "RPlayer",
    RInfo => "RInfo",
    RCommit => "RCommit",
    RKey => "RKey",
    RPacked => "RPacked",
);

/// A value that can be passed as one kernel parameter.
pub(crate) trait KernelParam: Copy {
    /// The parameter's C type, without `const` or `*`.
    #[allow(dead_code)] // Read only by the signature test.
    const C_TYPE: &'static str;
    /// Whether the parameter is a pointer.
    #[allow(dead_code)] // Read only by the signature test.
    const POINTER: bool;
    /// The driver's argument slot.
    fn arg(self) -> Arg;
}

impl KernelParam for u32 {
    const C_TYPE: &'static str = "u32";
    const POINTER: bool = false;
    fn arg(self) -> Arg {
        Arg::U(self)
    }
}

impl KernelParam for u64 {
    const C_TYPE: &'static str = "u64";
    const POINTER: bool = false;
    fn arg(self) -> Arg {
        Arg::L(self)
    }
}

impl KernelParam for f32 {
    const C_TYPE: &'static str = "float";
    const POINTER: bool = false;
    fn arg(self) -> Arg {
        Arg::F(self)
    }
}

impl<T: DeviceItem> KernelParam for DevPtr<T> {
    const C_TYPE: &'static str = T::C_TYPE;
    const POINTER: bool = true;
    fn arg(self) -> Arg {
        Arg::P(self.raw)
    }
}

/// A kernel's full argument list.
pub(crate) trait Kernel {
    /// The kernel's entry point in the module.
    const NAME: &'static str;
    /// Calls `f` with the argument slots, in the kernel's parameter order.
    fn with_args<R>(&self, f: impl FnOnce(&[Arg]) -> R) -> R;
}

impl Gpu {
    /// Launches kernel `K` on `grid` blocks of `block` threads.
    pub fn launch_grid<K: Kernel>(&self, grid: u32, block: u32, kernel: K) -> Result<(), PhysicsError> {
        kernel.with_args(|args| self.launch_raw(K::NAME, grid, block, args))
    }

    /// Launches kernel `K` with one thread per item, 256 a block.
    pub fn launch<K: Kernel>(&self, items: usize, kernel: K) -> Result<(), PhysicsError> {
        self.launch_grid(items.div_ceil(256) as u32, 256, kernel)
    }
}

/// Declares one argument struct per kernel, its [`Kernel`] impl, and (for the tests) the
/// list of every kernel's parameters as the structs declare them.
macro_rules! kernels {
    ($(
        $(#[$doc:meta])*
        $name:ident = $cname:literal { $($field:ident: $ty:ty),* $(,)? }
    )*) => {
        $(
            $(#[$doc])*
            #[derive(Clone, Copy)]
            pub(crate) struct $name {
                $(
                    #[doc = concat!("The kernel's `", stringify!($field), "`.")]
                    pub $field: $ty,
                )*
            }

            impl Kernel for $name {
                const NAME: &'static str = $cname;
                fn with_args<R>(&self, f: impl FnOnce(&[Arg]) -> R) -> R {
                    f(&[$(KernelParam::arg(self.$field)),*])
                }
            }
        )*

        /// Every kernel with its parameters (name, C type, pointer) as declared here.
        #[cfg(test)]
        fn declared_structs() -> Vec<(&'static str, Vec<(&'static str, &'static str, bool)>)> {
            vec![$(
                ($cname, vec![$((stringify!($field), <$ty as KernelParam>::C_TYPE, <$ty as KernelParam>::POINTER)),*]),
            )*]
        }
    };
}

kernels! {
    /// `k_replica_objects` (`kernels/replica.cu`): a thread an object gathers its
    /// position (quantized too), id and shape into one 32-byte `RObj` for the build.
    KReplicaObjects = "k_replica_objects" {
        n: u32,
        pos: DevPtr<f32>,
        ids: DevPtr<u32>,
        shapes: DevPtr<u8>,
        objs: DevPtr<RObj>,
    }
    /// `k_replica_due` (`kernels/replica.cu`): one warp per player matches its view
    /// with its tracks, applies its acknowledgements and finds the objects due (steps 1
    /// and 2 of `replica.cuh`'s `r_select`); `counts` gets how many of each.
    KReplicaDue = "k_replica_due" {
        nq: u32,
        cfg: DevPtr<RConfig>,
        tick: u64,
        build: u64,
        offsets: DevPtr<u32>,
        objects: DevPtr<u32>,
        n: u32,
        objs: DevPtr<RObj>,
        players: DevPtr<RPlayer>,
        homes: DevPtr<RHome>,
        old_tracks: DevPtr<RTrack>,
        next_tracks: DevPtr<RTrack>,
        taken: DevPtr<u64>,
        cands: DevPtr<RCand>,
        un: DevPtr<RKey>,
        orph: DevPtr<RKey>,
        moved: DevPtr<RMoved>,
        wanted: DevPtr<RDue>,
        flights: DevPtr<RFlight>,
        states: DevPtr<RState>,
        counts: DevPtr<u32>,
        info: DevPtr<RInfo>,
    }
    /// `k_replica_rank`: one block per player sorts its objects due by urgency into
    /// `ranked`.
    KReplicaRank = "k_replica_rank" {
        nq: u32,
        offsets: DevPtr<u32>,
        counts: DevPtr<u32>,
        wanted: DevPtr<RDue>,
        ranked: DevPtr<RDue>,
    }
    /// `k_replica_take`: one warp per player takes its ranked objects into its budget,
    /// the chosen records sorted by id (step 3 of `r_select`); its counts to the host
    /// (`info`, mapped) and to `k_replica_pack` (`infos`).
    KReplicaTake = "k_replica_take" {
        nq: u32,
        cfg: DevPtr<RConfig>,
        tick: u64,
        offsets: DevPtr<u32>,
        n: u32,
        objs: DevPtr<RObj>,
        players: DevPtr<RPlayer>,
        homes: DevPtr<RHome>,
        next_tracks: DevPtr<RTrack>,
        cands: DevPtr<RCand>,
        counts: DevPtr<u32>,
        ranked: DevPtr<RDue>,
        chosen: DevPtr<RChosen>,
        info: DevPtr<RInfo>,
        infos: DevPtr<RInfo>,
    }
    /// `k_replica_pack` (`kernels/pack.cu`): one warp per player packs its chosen records
    /// and its own into delta update bodies (`pack.cuh`'s `r_pack`, `pack_deltas`' rules,
    /// its passes shared by the lanes) in shared memory and stores them into mapped host
    /// memory (`out`, `out_lens`, `packed`); `ends` stays on the device.
    KReplicaPack = "k_replica_pack" {
        nq: u32,
        cfg: DevPtr<RConfig>,
        tick: u64,
        dilation: u32,
        offsets: DevPtr<u32>,
        players: DevPtr<RPlayer>,
        counts: DevPtr<u32>,
        infos: DevPtr<RInfo>,
        chosen: DevPtr<RChosen>,
        ends: DevPtr<u32>,
        packed: DevPtr<RPacked>,
        out: DevPtr<u8>,
        out_lens: DevPtr<u32>,
    }
    /// `k_replica_commit`: one warp per player takes what its datagrams took (the steps
    /// of `r_commit`).
    KReplicaCommit = "k_replica_commit" {
        nq: u32,
        cfg: DevPtr<RConfig>,
        tick: u64,
        offsets: DevPtr<u32>,
        players: DevPtr<RPlayer>,
        homes: DevPtr<RHome>,
        commits: DevPtr<RCommit>,
        ends: DevPtr<u32>,
        chosen: DevPtr<RChosen>,
        cands: DevPtr<RCand>,
        next_tracks: DevPtr<RTrack>,
        flights: DevPtr<RFlight>,
        states: DevPtr<RState>,
    }
    /// `k_replica_carry`: the tracks of players left out of a build, into its buffer.
    KReplicaCarry = "k_replica_carry" {
        count: u32,
        carry: DevPtr<u32>,
        old_tracks: DevPtr<RTrack>,
        next_tracks: DevPtr<RTrack>,
        homes: DevPtr<RHome>,
    }

    /// `k_scan_blocks` (`kernels/scan.cu`): scans each block of `data` in place and
    /// writes each block's total to `block_sums`.
    KScanBlocks = "k_scan_blocks" { data: DevPtr<u32>, len: u32, block_sums: DevPtr<u32> }
    /// `k_scan_sums`: one block scans `sums[0..len]` in place.
    KScanSums = "k_scan_sums" { sums: DevPtr<u32>, len: u32 }
    /// `k_scan_add`: adds each block's scanned total back to its items.
    KScanAdd = "k_scan_add" { data: DevPtr<u32>, len: u32, sums: DevPtr<u32> }

    /// `k_boxes_morton` (`kernels/lbvh.cu`): object boxes and the Morton codes of their
    /// centres in the frame `(m, s)`, with the identity order as the sort's values.
    KBoxesMorton = "k_boxes_morton" {
        n: u32,
        pos: DevPtr<f32>,
        half: DevPtr<f32>,
        boxes: DevPtr<f32>,
        keys: DevPtr<u64>,
        vals: DevPtr<u32>,
        mx: f32,
        my: f32,
        mz: f32,
        sx: f32,
        sy: f32,
        sz: f32,
    }
    /// `k_radix_counts`: the digit counts of every radix pass.
    KRadixCounts = "k_radix_counts" { keys: DevPtr<u64>, n: u32, hist: DevPtr<u32> }
    /// `k_radix_pass`: one stable 8-bit pass of the one-sweep radix sort.
    KRadixPass = "k_radix_pass" {
        keys_in: DevPtr<u64>,
        vals_in: DevPtr<u32>,
        keys_out: DevPtr<u64>,
        vals_out: DevPtr<u32>,
        n: u32,
        pass: u32,
        hist: DevPtr<u32>,
        status: DevPtr<u32>,
        tile_counter: DevPtr<u32>,
    }
    /// `k_emit`: Karras's emission of the internal nodes over sorted codes.
    KEmit = "k_emit" {
        keys: DevPtr<u64>,
        n: u32,
        nodes: DevPtr<Node>,
        node_parent: DevPtr<u32>,
        leaf_parent: DevPtr<u32>,
    }
    /// `k_refit`: bottom-up node boxes, one arrival counter per node.
    KRefit = "k_refit" {
        n: u32,
        order: DevPtr<u32>,
        boxes: DevPtr<f32>,
        nodes: DevPtr<Node>,
        node_parent: DevPtr<u32>,
        leaf_parent: DevPtr<u32>,
        arrivals: DevPtr<u32>,
    }

    /// `k_tree_count` (`kernels/broad.cu`): per query, the tree targets its box overlaps.
    KTreeCount = "k_tree_count" {
        nq: u32,
        qboxes: DevPtr<f32>,
        qorder: DevPtr<u32>,
        exclude_self: u32,
        nodes: DevPtr<Node>,
        order: DevPtr<u32>,
        nleaves: u32,
        tboxes: DevPtr<f32>,
        counts: DevPtr<u32>,
        scratch: DevPtr<u32>,
        slots: u32,
    }
    /// `k_tree_write`: per query, its sorted tree targets at its scanned offset.
    KTreeWrite = "k_tree_write" {
        nq: u32,
        qboxes: DevPtr<f32>,
        qorder: DevPtr<u32>,
        exclude_self: u32,
        nodes: DevPtr<Node>,
        order: DevPtr<u32>,
        nleaves: u32,
        tboxes: DevPtr<f32>,
        offsets: DevPtr<u32>,
        out: DevPtr<u32>,
        cap: u32,
        scratch: DevPtr<u32>,
        slots: u32,
    }
    /// `k_sort_ranges`: each query's range of `objects` sorted ascending, a block each.
    KSortRanges = "k_sort_ranges" { nq: u32, offsets: DevPtr<u32>, objects: DevPtr<u32> }
    /// `k_grid_keys` (`kernels/grid.cu`): each object's column, the columns' populations
    /// and the widest object's width.
    KGridKeys = "k_grid_keys" {
        n: u32,
        boxes: DevPtr<f32>,
        ox: f32,
        oz: f32,
        inv: f32,
        g: u32,
        keys: DevPtr<u32>,
        cells: DevPtr<u32>,
        wmax: DevPtr<u32>,
    }
    /// `k_grid_scatter`: the objects' slots and boxes in column order.
    KGridScatter = "k_grid_scatter" {
        n: u32,
        keys: DevPtr<u32>,
        cells: DevPtr<u32>,
        boxes: DevPtr<f32>,
        gboxes: DevPtr<f32>,
        gslots: DevPtr<u32>,
    }
    /// `k_grid_pass`: a warp a query, counting the objects its box overlaps (`out`
    /// null) or writing them at its scanned offset (unsorted).
    KGridPass = "k_grid_pass" {
        nq: u32,
        qboxes: DevPtr<f32>,
        qorder: DevPtr<u32>,
        ox: f32,
        oz: f32,
        inv: f32,
        g: u32,
        cells: DevPtr<u32>,
        gboxes: DevPtr<f32>,
        gslots: DevPtr<u32>,
        wmax: DevPtr<u32>,
        counts: DevPtr<u32>,
        out: DevPtr<u32>,
        cap: u32,
    }
    /// `k_naive_count`: per query, the targets its box overlaps, testing all `nt`.
    KNaiveCount = "k_naive_count" {
        nq: u32,
        qboxes: DevPtr<f32>,
        exclude_self: u32,
        nt: u32,
        tboxes: DevPtr<f32>,
        counts: DevPtr<u32>,
    }
    /// `k_naive_write`: per query, its targets (all `nt` tested) at its scanned offset.
    KNaiveWrite = "k_naive_write" {
        nq: u32,
        qboxes: DevPtr<f32>,
        exclude_self: u32,
        nt: u32,
        tboxes: DevPtr<f32>,
        offsets: DevPtr<u32>,
        out: DevPtr<u32>,
        cap: u32,
    }
    /// `k_boxes`: the boxes `pos ± half` (no tree: `cuda-naive`).
    KBoxes = "k_boxes" { n: u32, pos: DevPtr<f32>, half: DevPtr<f32>, boxes: DevPtr<f32> }

    /// `k_narrow_static` (`kernels/physics.cu`): each object's responses to its static
    /// pairs, summed in the CPU's order.
    KNarrowStatic = "k_narrow_static" {
        n: u32,
        kp: DevPtr<DeviceParams>,
        pos: DevPtr<f32>,
        prev: DevPtr<f32>,
        half: DevPtr<f32>,
        radius: DevPtr<f32>,
        shape: DevPtr<u8>,
        spos: DevPtr<f32>,
        shalf: DevPtr<f32>,
        sradius: DevPtr<f32>,
        sshape: DevPtr<u8>,
        offsets: DevPtr<u32>,
        prims: DevPtr<u32>,
        cap: u32,
        acc: DevPtr<f32>,
        sup: DevPtr<u8>,
        counters: DevPtr<u32>,
    }
    /// `k_narrow_dynamic`: each object's responses to its dynamic pairs, added on top.
    KNarrowDynamic = "k_narrow_dynamic" {
        n: u32,
        kp: DevPtr<DeviceParams>,
        pos: DevPtr<f32>,
        prev: DevPtr<f32>,
        half: DevPtr<f32>,
        radius: DevPtr<f32>,
        shape: DevPtr<u8>,
        offsets: DevPtr<u32>,
        others: DevPtr<u32>,
        cap: u32,
        acc: DevPtr<f32>,
        sup: DevPtr<u8>,
        counters: DevPtr<u32>,
    }
    /// `k_forces`: NPC decisions, forces, terrain and integration.
    KForces = "k_forces" {
        n: u32,
        kp: DevPtr<DeviceParams>,
        seed: u64,
        tick: u64,
        period: u32,
        turn_phase: u32,
        pos: DevPtr<f32>,
        prev: DevPtr<f32>,
        half: DevPtr<f32>,
        kind: DevPtr<u8>,
        id: DevPtr<u32>,
        action: DevPtr<u8>,
        flags: DevPtr<u8>,
        acc: DevPtr<f32>,
        sup: DevPtr<u8>,
        samples: DevPtr<u16>,
    }

    /// `k_patch_gather` (`kernels/patch.cu`): each new slot covered by a run copies its
    /// object's nine arrays from the old slot into the `out_` arrays.
    KPatchGather = "k_patch_gather" {
        n: u32,
        runs: DevPtr<u32>,
        nruns: u32,
        pos: DevPtr<f32>,
        prev: DevPtr<f32>,
        half: DevPtr<f32>,
        radius: DevPtr<f32>,
        shape: DevPtr<u8>,
        kind: DevPtr<u8>,
        id: DevPtr<u32>,
        action: DevPtr<u8>,
        flags: DevPtr<u8>,
        out_pos: DevPtr<f32>,
        out_prev: DevPtr<f32>,
        out_half: DevPtr<f32>,
        out_radius: DevPtr<f32>,
        out_shape: DevPtr<u8>,
        out_kind: DevPtr<u8>,
        out_id: DevPtr<u32>,
        out_action: DevPtr<u8>,
        out_flags: DevPtr<u8>,
    }
    /// `k_patch_scatter`: the `w` states staged by the host written into their slots.
    KPatchScatter = "k_patch_scatter" {
        w: u32,
        staged: DevPtr<u32>,
        n: u32,
        pos: DevPtr<f32>,
        prev: DevPtr<f32>,
        half: DevPtr<f32>,
        radius: DevPtr<f32>,
        shape: DevPtr<u8>,
        kind: DevPtr<u8>,
        id: DevPtr<u32>,
        action: DevPtr<u8>,
        flags: DevPtr<u8>,
    }
    /// `k_gather_positions` (`kernels/patch.cu`): the positions of `m` slots out of
    /// `pos`, each slot's three floats into `out`.
    KGatherPositions = "k_gather_positions" {
        m: u32,
        slots: DevPtr<u32>,
        pos: DevPtr<f32>,
        out: DevPtr<f32>,
    }

}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compile;

    /// A kernel's name and its parameters as (name, C type without `const` and `*`,
    /// pointer).
    type Signature = (String, Vec<(String, String, bool)>);

    /// Every `extern "C" __global__` function of the sources as (name, [(parameter name,
    /// C type without `const` and `*`, pointer)]).
    fn kernel_signatures() -> Vec<Signature> {
        let mut out: Vec<Signature> = compile::kernel_declarations()
            .into_iter()
            .map(|(name, params)| {
                let params = params
                    .split(',')
                    .map(|p| {
                        let p = p.split_whitespace().collect::<Vec<_>>().join(" ");
                        let pointer = p.contains('*');
                        let p = p.replace('*', " ");
                        let words: Vec<&str> = p.split_whitespace().filter(|w| *w != "const").collect();
                        let (name, ty) = words.split_last().expect("a parameter");
                        (name.to_string(), ty.join(" "), pointer)
                    })
                    .collect();
                (name.to_string(), params)
            })
            .collect();
        out.sort();
        out
    }

    #[test]
    fn every_kernel_struct_matches_its_kernel_signature() {
        let mut structs: Vec<Signature> = declared_structs()
            .into_iter()
            .map(|(k, ps)| (k.to_string(), ps.into_iter().map(|(n, t, p)| (n.to_string(), t.to_string(), p)).collect()))
            .collect();
        structs.sort();
        let sources = kernel_signatures();
        assert_eq!(structs.len(), sources.len(), "kernels with no struct, or structs with no kernel");
        for (s, k) in structs.iter().zip(&sources) {
            assert_eq!(s, k, "the launch struct of {} differs from its C++ signature", k.0);
        }
    }

    #[test]
    fn every_kernel_struct_is_in_the_load_table() {
        let mut table: Vec<(String, usize)> = compile::KERNELS.iter().map(|(n, a)| (n.to_string(), *a)).collect();
        table.sort();
        let mut structs: Vec<(String, usize)> =
            declared_structs().into_iter().map(|(k, ps)| (k.to_string(), ps.len())).collect();
        structs.sort();
        assert_eq!(structs, table);
    }

    #[test]
    fn pointer_arithmetic_counts_items() {
        let p = DevPtr::<u32>::from_raw(1000);
        assert_eq!(p.add(3).raw(), 1012);
        assert_eq!(DevPtr::<u64>::from_raw(0).add(2).raw(), 16);
        assert_eq!(DevPtr::<Node>::from_raw(0).add(1).raw(), 64);
    }
}
