// The only file that includes pybind11: checks, pointers, outputs, GIL.
// It is over the package's 800-line mark on purpose: one file holds every binding's
// checks and GIL release, so the rest of csrc/ knows nothing of Python.
//
// gesturedb/search.py validates every argument with messages for users; the
// checks here are the backstop that keeps C++ from reading out of bounds if
// _core is called directly. Arrays are taken with .noconvert(): a float64 or
// non-contiguous database is refused, never silently copied (it is hundreds
// of megabytes). Outputs are allocated before the GIL is released, and only
// pure C++ runs without it.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <array>
#include <cstring>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

#include "assembly.h"
#include "fk.h"
#include "ik.h"
#include "kernels.h"
#include "preselect.h"
#include "seams.h"
#include "search.h"
#include "threads.h"

namespace py = pybind11;
using namespace gesturedb;

namespace {

using F32 = py::array_t<float, py::array::c_style>;
using I64 = py::array_t<int64_t, py::array::c_style>;
using U64 = py::array_t<uint64_t, py::array::c_style>;
using Bool = py::array_t<bool, py::array::c_style>;
using U16 = py::array_t<uint16_t, py::array::c_style>;
using F64 = py::array_t<double, py::array::c_style>;

std::string shape_str(const py::array& a) {
    std::string s = "(";
    for (py::ssize_t i = 0; i < a.ndim(); ++i) {
        if (i) s += ", ";
        s += std::to_string(a.shape(i));
    }
    if (a.ndim() == 1) s += ",";
    return s + ")";
}

void require_ndim(const py::array& a, int ndim, const char* name) {
    if (a.ndim() != ndim)
        throw std::invalid_argument(std::string(name) + ": expected " + std::to_string(ndim) +
                                    "-d array; got shape " + shape_str(a));
}

Span2<const float> span2(const F32& a, const char* name) {
    require_ndim(a, 2, name);
    return {a.data(), int64_t(a.shape(0)), int64_t(a.shape(1))};
}

Database make_db(const F32& pose, const F32& audio, const I64& seg_start, const I64& seg_len,
                 const std::optional<U16>& pose_f16 = std::nullopt,
                 const std::optional<py::tuple>& pose_proj = std::nullopt) {
    Database db;
    db.pose = span2(pose, "pose");
    if (pose_proj) {
        // (blocks float32 (ceil(F/16), J, 16), basis float64 (Dp, J-1), mean float64 (Dp,), max norm)
        if (pose_proj->size() != 4) throw std::invalid_argument("pose_proj: expected a 4-tuple");
        // refuse anything cast would have to copy: a copy would die with this scope
        const bool half = py::isinstance<U16>((*pose_proj)[0]);
        if (!(half || py::isinstance<F32>((*pose_proj)[0])) || !py::isinstance<F64>((*pose_proj)[1]) ||
            !py::isinstance<F64>((*pose_proj)[2]))
            throw std::invalid_argument(
                "pose_proj: expected float32 (or binary16 as uint16) blocks and float64 basis and mean, "
                "C-contiguous");
        const F64 basis = (*pose_proj)[1].cast<F64>();
        const F64 mean = (*pose_proj)[2].cast<F64>();
        // the tuple's arrays are owned by the caller's PoseProjection; cast
        // returned views of them (already of these dtypes and C-contiguous,
        // checked in Python), so these pointers stay valid for the call
        auto set_blocks = [&](const auto& rows, auto& span) {
            require_ndim(rows, 3, "pose_proj blocks");
            if (rows.shape(2) != kFrameBlock)
                throw std::invalid_argument("pose_proj blocks: expected (ceil(F/16), J, 16); got " +
                                            shape_str(rows));
            span = {rows.data(), int64_t(rows.shape(0)), int64_t(rows.shape(1)) * kFrameBlock};
            db.proj_dim = int64_t(rows.shape(1));
        };
        if (half) set_blocks((*pose_proj)[0].cast<U16>(), db.proj_f16);
        else set_blocks((*pose_proj)[0].cast<F32>(), db.proj);
        require_ndim(basis, 2, "pose_proj basis");
        require_ndim(mean, 1, "pose_proj mean");
        db.proj_basis = {basis.data(), int64_t(basis.shape(0)), int64_t(basis.shape(1))};
        db.proj_mean = {mean.data(), int64_t(mean.shape(0))};
        db.proj_max_norm = (*pose_proj)[3].cast<double>();
    }
    if (pose_f16) {
        require_ndim(*pose_f16, 2, "pose_f16");
        db.pose_f16 = {pose_f16->data(), int64_t(pose_f16->shape(0)), int64_t(pose_f16->shape(1))};
    }
    db.audio = span2(audio, "audio");
    require_ndim(seg_start, 1, "seg_start");
    require_ndim(seg_len, 1, "seg_len");
    db.seg_start = {seg_start.data(), int64_t(seg_start.shape(0))};
    db.seg_len = {seg_len.data(), int64_t(seg_len.shape(0))};
    check_database(db);
    return db;
}

Preselect parse_preselect(const std::string& s) {
    if (s == "pose") return Preselect::Pose;
    if (s == "audio") return Preselect::Audio;
    throw std::invalid_argument("preselect: expected 'pose' or 'audio'; got '" + s + "'");
}

template <typename Array>
void check_vector(const Array& v, int64_t len, const char* name) {
    require_ndim(v, 1, name);
    if (v.shape(0) != len)
        throw std::invalid_argument(std::string(name) + ": expected " + std::to_string(len) +
                                    " values; got " + std::to_string(v.shape(0)));
}

// Candidate starts of a table, starts[m] for segment m: a window of n frames
// must lie inside its segment, after its entry frame (spec step 1), or -1.
void check_starts(const Database& db, const int64_t* starts, int64_t n) {
    for (int64_t m = 0; m < db.n_segments(); ++m) {
        if (starts[m] != -1 && (starts[m] < 1 || starts[m] > db.seg_len[m] - n))
            throw std::invalid_argument("starts[" + std::to_string(m) + "]: expected -1 or 1 <= s <= " +
                                        std::to_string(db.seg_len[m] - n) + " (segment of " +
                                        std::to_string(db.seg_len[m]) + " frames, window of " +
                                        std::to_string(n) + "); got " + std::to_string(starts[m]));
    }
}

const bool* exclude_ptr(const std::optional<Bool>& exclude, int64_t M) {
    if (!exclude) return nullptr;
    require_ndim(*exclude, 1, "exclude");
    if (exclude->shape(0) != M)
        throw std::invalid_argument("exclude: expected " + std::to_string(M) + " entries; got " +
                                    std::to_string(exclude->shape(0)));
    return exclude->data();
}

// Exclusion for Q queries: one (M,) row for all, or (Q, M) one row each.
// row(i) is query i's (null: none excluded).
struct BatchExclude {
    const bool* data = nullptr;
    bool per_query = false;
    int64_t M = 0;
    const bool* row(int64_t i) const { return data == nullptr ? nullptr : (per_query ? data + i * M : data); }
};

BatchExclude batch_exclude(const std::optional<Bool>& exclude, int64_t Q, int64_t M) {
    BatchExclude b;
    b.M = M;
    if (!exclude) return b;
    const Bool& e = *exclude;
    if (e.ndim() == 1 && e.shape(0) == M) {
        b.data = e.data();
    } else if (e.ndim() == 2 && e.shape(0) == Q && e.shape(1) == M) {
        b.data = e.data();
        b.per_query = true;
    } else {
        throw std::invalid_argument("exclude: expected (" + std::to_string(M) + ",) or (" +
                                    std::to_string(Q) + ", " + std::to_string(M) + "); got " + shape_str(e));
    }
    return b;
}

BatchMethod parse_method(const std::string& method) {
    if (method == "auto") return BatchMethod::Auto;
    if (method == "blocked") return BatchMethod::Blocked;
    if (method == "per_query") return BatchMethod::PerQuery;
    throw std::invalid_argument("method: expected 'auto', 'blocked' or 'per_query'; got '" + method + "'");
}

AllowedSchedule make_allowed(const std::optional<U64>& allowed, const Database& db, bool allow_2d) {
    AllowedSchedule s;
    if (!allowed) return s;
    const int64_t words = (db.n_frames() + 63) / 64;
    const U64& a = *allowed;
    if (a.ndim() == 1 || (allow_2d && a.ndim() == 2)) {
        const int64_t cols = a.shape(a.ndim() - 1);
        if (cols != words)
            throw std::invalid_argument("allowed: expected " + std::to_string(words) +
                                        " uint64 words per bitset; got shape " + shape_str(a));
        s.words = a.data();
        s.n_words = words;
        s.per_step = a.ndim() == 2;
        s.n_rows = a.ndim() == 2 ? a.shape(0) : 1;
        return s;
    }
    throw std::invalid_argument(std::string("allowed: expected ") + (allow_2d ? "1-d or 2-d" : "1-d") +
                                " uint64 array; got shape " + shape_str(a));
}

// A (Q, words) array of per-query bitsets (BatchPlan.tables) as each query's
// BatchQuery::allowed; rows with equal words point at the first of them, so
// that the blocked batch runs the queries of one bitset as one group.
void set_query_allowed(std::vector<BatchQuery>& batch, const U64& a, const Database& db) {
    const int64_t words = (db.n_frames() + 63) / 64, Q = int64_t(batch.size());
    if (a.ndim() != 2 || a.shape(0) != Q || a.shape(1) != words)
        throw std::invalid_argument("allowed: expected (" + std::to_string(Q) + ", " + std::to_string(words) +
                                    ") uint64 bitsets (one per query); got shape " + shape_str(a));
    const uint64_t* base = a.data();
    std::unordered_map<uint64_t, std::vector<int64_t>> seen;  // FNV-1a of a row -> rows with it
    for (int64_t i = 0; i < Q; ++i) {
        const uint64_t* row = base + i * words;
        uint64_t h = 1469598103934665603ull;
        for (int64_t w = 0; w < words; ++w) h = (h ^ row[w]) * 1099511628211ull;
        const uint64_t* use = row;
        auto& same = seen[h];
        for (int64_t j : same)
            if (std::memcmp(base + j * words, row, size_t(words) * 8) == 0) {
                use = base + j * words;
                break;
            }
        if (use == row) same.push_back(i);
        batch[i].has_allowed = true;
        batch[i].allowed = BitsetView{use, words};
    }
}

// Output arrays of a search, allocated with the GIL held.
struct SearchArrays {
    I64 segment, start, frame, length, out_frame;
    py::array_t<double> pose_dist, audio_dist;
    I64 pose_rank, audio_rank, n_candidates;

    explicit SearchArrays(int64_t S)
        : segment(S), start(S), frame(S), length(S), out_frame(S), pose_dist(S), audio_dist(S), pose_rank(S),
          audio_rank(S), n_candidates(S) {}

    SearchOutput view(int64_t offset = 0) {
        return {segment.mutable_data() + offset,    start.mutable_data() + offset,
                frame.mutable_data() + offset,      length.mutable_data() + offset,
                out_frame.mutable_data() + offset,  pose_dist.mutable_data() + offset,
                audio_dist.mutable_data() + offset, pose_rank.mutable_data() + offset,
                audio_rank.mutable_data() + offset, n_candidates.mutable_data() + offset};
    }

    py::dict to_dict() const {
        py::dict d;
        d["segments"] = segment;
        d["starts"] = start;
        d["frames"] = frame;
        d["lengths"] = length;
        d["out_frames"] = out_frame;
        d["pose_dist"] = pose_dist;
        d["audio_dist"] = audio_dist;
        d["pose_rank"] = pose_rank;
        d["audio_rank"] = audio_rank;
        d["n_candidates"] = n_candidates;
        return d;
    }
};

py::dict step_result_dict(const StepResult& r) {
    py::dict d;
    d["found"] = r.found;
    d["segment"] = r.segment;
    d["start"] = r.start;
    d["frame"] = r.frame;
    d["length"] = r.length;
    d["pose_dist"] = r.pose_dist;
    d["audio_dist"] = r.audio_dist;
    d["pose_rank"] = r.pose_rank;
    d["audio_rank"] = r.audio_rank;
    d["n_candidates"] = r.n_candidates;
    return d;
}

// The kinematic chain both forward kinematics bindings take: root (F, 3), parents (J,) with every
// joint after its parent, offsets (J, 3); checked here, a wrong shape or order would read out of
// bounds. Returns the parents' data.
const int64_t* check_chain(const F64& root, const I64& parents, const F64& offsets, int64_t F, int64_t J) {
    if (root.ndim() != 2 || root.shape(0) != F || root.shape(1) != 3)
        throw std::invalid_argument("root: expected (" + std::to_string(F) + ", 3); got " + shape_str(root));
    if (parents.ndim() != 1 || parents.shape(0) != J)
        throw std::invalid_argument("parents: expected (" + std::to_string(J) + ",); got " +
                                    shape_str(parents));
    if (offsets.ndim() != 2 || offsets.shape(0) != J || offsets.shape(1) != 3)
        throw std::invalid_argument("offsets: expected (" + std::to_string(J) + ", 3); got " +
                                    shape_str(offsets));
    const int64_t* par = parents.data();
    for (int64_t j = 1; j < J; ++j)
        if (par[j] < 0 || par[j] >= j)
            throw std::invalid_argument("parents[" + std::to_string(j) + "]: expected 0 <= parent < " +
                                        std::to_string(j) + " (parents first); got " +
                                        std::to_string(par[j]));
    return par;
}

}  // namespace

PYBIND11_MODULE(_core, m) {
    m.doc() = "gesturedb C++ core: SIMD rank-sum motion-matching search (see gesturedb.search)";
    // choose the kernel table now so that a bad GESTUREDB_SIMD fails the import
    active_kernels();

    m.def(
        "kernels",
        []() {
            const char* names[8];
            const int n = available_isas(names, 8);
            std::vector<std::string> out(names, names + std::min(n, 8));
            return out;
        },
        "Instruction sets this build and CPU can run, narrowest first.");
    m.def(
        "get_simd", []() { return std::string(active_kernels().isa); },
        "The instruction set the next search will use.");
    m.def(
        "set_simd", [](const std::string& isa) { set_simd(isa.c_str()); }, py::arg("isa"),
        "Switch the instruction set for subsequent searches ('scalar', 'avx2', 'avx512').");
    m.def(
        "blocked_min_queries",
        [](int threads) { return blocked_min_queries(threads > 0 ? threads : default_threads()); },
        py::arg("threads"),
        "Queries from which method='auto' takes the blocked path with `threads` threads (<= 0: "
        "default_threads()).");
    m.def("default_threads", &default_threads,
          "Threads used when a call passes threads <= 0: the CPUs in this process's affinity mask, "
          "bounded by the cgroup CPU quota, at least 1.");
    m.def("cgroup_cpu_limit", &cgroup_cpu_limit, py::arg("root"),
          "The CPU quota of the cgroup mounted at root, in whole CPUs rounded up; 0 when there is none.");

    // --- raw kernels, for tests and benchmarks --------------------------------
    m.def(
        "l2sq_rows_f32",
        [](const F32& rows, const F32& v, const std::string& isa) {
            const Kernels& k = kernels_for(isa.c_str());
            const Span2<const float> r = span2(rows, "rows");
            check_vector(v, r.cols, "v");
            py::array_t<float> out(r.rows);
            float* o = out.mutable_data();
            {
                py::gil_scoped_release release;
                k.l2sq_rows_f32(r.data, r.rows, r.cols, v.data(), o);
            }
            return out;
        },
        py::arg("rows").noconvert(), py::arg("v").noconvert(), py::arg("isa"),
        "out[r] = ||rows[r] - v||^2 with the kernel of one instruction set.");

    m.def(
        "l2sq_rows_f16",
        [](const U16& rows, const F32& v, const std::string& isa) {
            const Kernels& k = kernels_for(isa.c_str());
            require_ndim(rows, 2, "rows");
            const int64_t R = rows.shape(0), D = rows.shape(1);
            check_vector(v, D, "v");
            py::array_t<float> d(R);
            float* pd = d.mutable_data();
            {
                py::gil_scoped_release release;
                k.l2sq_rows_f16(rows.data(), R, D, v.data(), pd);
            }
            return d;
        },
        py::arg("rows").noconvert(), py::arg("v").noconvert(), py::arg("isa"),
        "||h - v||^2 per row of binary16 bit patterns h, with one instruction set.");

    // float32 or binary16 blocks: the same checks and call, only the kernel differs
    auto blocks_fn = [](auto kernel_of) {
        return [kernel_of](const auto& blocks, int64_t f0, int64_t f1, const F32& v, const std::string& isa,
                           std::optional<std::array<float, 3>> up) {
            const Kernels& k = kernels_for(isa.c_str());
            require_ndim(blocks, 3, "blocks");
            if (blocks.shape(2) != kFrameBlock)
                throw std::invalid_argument("blocks: expected (n_blocks, dim, 16); got " + shape_str(blocks));
            const int64_t D = blocks.shape(1);
            check_vector(v, D, "v");
            if (f0 < 0 || f1 < f0 || f1 > int64_t(blocks.shape(0)) * kFrameBlock)
                throw std::invalid_argument("[f0, f1): expected inside [0, " +
                                            std::to_string(blocks.shape(0) * kFrameBlock) + ")");
            py::array_t<float> d(f1 - f0);
            float* pd = d.mutable_data();
            float umin;
            {
                py::gil_scoped_release release;
                umin = kernel_of(k)(blocks.data(), f0, f1, D, v.data(), up ? up->data() : nullptr, pd);
            }
            return py::make_tuple(d, umin);
        };
    };
    const char* blocks_doc =
        "(||z_f - v||^2 for frames f in [f0, f1) stored in blocks of 16, and with up = (a, b, c) the\n"
        "smallest a d_f + b z_f[-1] + c, +inf without), with one instruction set.";
    m.def(
        "l2sq_blocks_f32",
        [f = blocks_fn([](const Kernels& k) { return k.l2sq_blocks_f32; })](
            const F32& blocks, int64_t f0, int64_t f1, const F32& v, const std::string& isa,
            std::optional<std::array<float, 3>> up) { return f(blocks, f0, f1, v, isa, up); },
        py::arg("blocks").noconvert(), py::arg("f0"), py::arg("f1"), py::arg("v").noconvert(), py::arg("isa"),
        py::arg("up") = py::none(), blocks_doc);
    m.def(
        "l2sq_blocks_f16",
        [f = blocks_fn([](const Kernels& k) { return k.l2sq_blocks_f16; })](
            const U16& blocks, int64_t f0, int64_t f1, const F32& v, const std::string& isa,
            std::optional<std::array<float, 3>> up) { return f(blocks, f0, f1, v, isa, up); },
        py::arg("blocks").noconvert(), py::arg("f0"), py::arg("f1"), py::arg("v").noconvert(), py::arg("isa"),
        py::arg("up") = py::none(), "The same over binary16 bit patterns (uint16 blocks).");

    m.def(
        "l2sq_pairs_f32",
        [](const F32& rows, const F32& vs, const I64& ri, const I64& vi, const std::string& isa) {
            const Kernels& k = kernels_for(isa.c_str());
            const Span2<const float> r = span2(rows, "rows"), v = span2(vs, "vs");
            if (v.cols != r.cols)
                throw std::invalid_argument("vs: expected " + std::to_string(r.cols) + " columns");
            require_ndim(ri, 1, "ri");
            require_ndim(vi, 1, "vi");
            const int64_t n = ri.shape(0);
            if (vi.shape(0) != n) throw std::invalid_argument("vi: expected the length of ri");
            std::vector<const float*> pr(n), pv(n);
            for (int64_t i = 0; i < n; ++i) {
                if (ri.data()[i] < 0 || ri.data()[i] >= r.rows || vi.data()[i] < 0 || vi.data()[i] >= v.rows)
                    throw std::invalid_argument("ri/vi: index out of range");
                pr[i] = r.row(ri.data()[i]);
                pv[i] = v.row(vi.data()[i]);
            }
            py::array_t<float> out(n);
            float* o = out.mutable_data();
            {
                py::gil_scoped_release release;
                k.l2sq_pairs_f32(pr.data(), pv.data(), n, r.cols, o);
            }
            return out;
        },
        py::arg("rows").noconvert(), py::arg("vs").noconvert(), py::arg("ri").noconvert(),
        py::arg("vi").noconvert(), py::arg("isa"),
        "out[i] = ||rows[ri[i]] - vs[vi[i]]||^2 through the batch's pair kernel of one instruction set.");

    m.def(
        "cosdots_pairs_f32",
        [](const F32& audio, const I64& starts, const F32& qs, const I64& qi, const std::string& isa) {
            const Kernels& k = kernels_for(isa.c_str());
            const Span2<const float> a = span2(audio, "audio"), q = span2(qs, "qs");
            require_ndim(starts, 1, "starts");
            require_ndim(qi, 1, "qi");
            const int64_t n = starts.shape(0), len = q.cols;
            if (qi.shape(0) != n) throw std::invalid_argument("qi: expected the length of starts");
            std::vector<const float*> pw(n), pq(n);
            for (int64_t i = 0; i < n; ++i) {
                const int64_t g = starts.data()[i];
                if (g < 0 || g * a.cols + len > a.rows * a.cols || qi.data()[i] < 0 || qi.data()[i] >= q.rows)
                    throw std::invalid_argument("starts/qi: index out of range");
                pw[i] = a.row(g);
                pq[i] = q.row(qi.data()[i]);
            }
            py::array_t<float> out(n);
            float* o = out.mutable_data();
            {
                py::gil_scoped_release release;
                k.cosdots_pairs_f32(pw.data(), pq.data(), n, len, o);
            }
            return out;
        },
        py::arg("audio").noconvert(), py::arg("starts").noconvert(), py::arg("qs").noconvert(),
        py::arg("qi").noconvert(), py::arg("isa"),
        "qa[i] = <qs[qi[i]], the len(qs[0]) values of audio from frame starts[i]> through the batch's pair "
        "kernel.");

    m.def(
        "projfilter_f32",
        [](const F32& z, const F32& nrow, const F32& rres, const F32& x, const F32& lanes,
           const std::string& isa) {
            const Kernels& k = kernels_for(isa.c_str());
            const Span2<const float> zr = span2(z, "z"), xs = span2(x, "x"), par = span2(lanes, "lanes");
            const int64_t n = zr.rows, J = zr.cols, nl = xs.rows;
            check_vector(nrow, n, "nrow");
            check_vector(rres, n, "rres");
            if (xs.cols != J || par.rows != 6 || par.cols != nl || nl < 1)
                throw std::invalid_argument("x: expected (lanes, J) and lanes (6, lanes)");
            const int64_t qp = padded_lanes(nl), W = panel_width(qp);
            // panels of W lanes as the batch packs them; padding lanes: zero x, aup = alo = 1
            std::vector<float> xt(size_t(J) * qp, 0.0f), p(size_t(6) * qp, 0.0f);
            for (int64_t l = 0; l < qp; ++l) p[1 * qp + l] = p[4 * qp + l] = 1.0f;
            for (int64_t l = 0; l < nl; ++l) {
                for (int64_t j = 0; j < J; ++j) xt[panel_offset(l, J, W) + j * W] = xs(l, j);
                for (int64_t c = 0; c < 6; ++c) p[c * qp + l] = par(c, l);
            }
            const ProjLanes L{&p[0], &p[qp], &p[2 * qp], &p[3 * qp], &p[4 * qp], &p[5 * qp]};
            py::array_t<float> dh({n, qp}), umin(qp);
            py::array_t<uint64_t> keep({n, lane_words(qp)});
            float *pd = dh.mutable_data(), *pu = umin.mutable_data();
            uint64_t* pk = keep.mutable_data();
            {
                py::gil_scoped_release release;
                std::fill(pu, pu + qp, std::numeric_limits<float>::infinity());
                k.projfilter_f32(zr.data, n, J, nrow.data(), rres.data(), xt.data(), qp, L, pd, pu);
                k.projkeep_f32(pd, n, qp, L, pu, pk);
            }
            return py::make_tuple(dh, umin, keep);
        },
        py::arg("z").noconvert(), py::arg("nrow").noconvert(), py::arg("rres").noconvert(),
        py::arg("x").noconvert(), py::arg("lanes").noconvert(), py::arg("isa"),
        "The batch's projection filter over rows z against lanes x; lanes = (nq, aup, bup, cup, alo, clo). "
        "Returns (dh (n, qp), umin (qp,), keep bits (n, ceil(qp / 64))); qp: the lanes padded to 8, 16, 32 "
        "or a multiple of 64.");

    m.def(
        "cosdots_f32",
        [](const F32& audio, const F32& q, const std::string& isa) {
            const Kernels& k = kernels_for(isa.c_str());
            const Span2<const float> a = span2(audio, "audio");
            const Span2<const float> qs = span2(q, "q");
            if (qs.cols != a.cols || qs.rows < 1 || qs.rows > a.rows)
                throw std::invalid_argument("q: expected (n, " + std::to_string(a.cols) +
                                            ") with 1 <= n <= " + std::to_string(a.rows) + "; got " +
                                            shape_str(q));
            const int64_t n_win = a.rows - qs.rows + 1;
            py::array_t<float> qa(n_win), aa(n_win);
            float *pqa = qa.mutable_data(), *paa = aa.mutable_data();
            {
                py::gil_scoped_release release;
                k.cosdots_f32(a.data, n_win, a.cols, qs.rows * qs.cols, qs.data, pqa, paa);
            }
            return py::make_tuple(qa, aa);
        },
        py::arg("audio").noconvert(), py::arg("q").noconvert(), py::arg("isa"),
        "(<q, w>, <w, w>) for every window w of len(q) frames of audio (flattened).");

    // --- search -------------------------------------------------------------
    m.def(
        "step",
        [](const F32& pose, const F32& audio, const I64& seg_start, const I64& seg_len, const F32& prev,
           const F32& query, int64_t k, const std::string& preselect, const std::optional<U64>& allowed,
           const std::optional<Bool>& exclude, int threads, const std::optional<U16>& pose_f16,
           const std::optional<py::tuple>& pose_proj) {
            const Database db = make_db(pose, audio, seg_start, seg_len, pose_f16, pose_proj);
            check_vector(prev, db.pose.cols, "prev_pose");
            const Span2<const float> q = span2(query, "query_audio");
            if (q.cols != db.audio.cols || q.rows < 1)
                throw std::invalid_argument("query_audio: expected (n >= 1, " +
                                            std::to_string(db.audio.cols) + "); got " + shape_str(query));
            if (k < 1) throw std::invalid_argument("k: expected >= 1; got " + std::to_string(k));
            StepOptions opt;
            opt.k = k;
            opt.preselect = parse_preselect(preselect);
            opt.allowed = make_allowed(allowed, db, false).at(0);
            opt.exclude = exclude_ptr(exclude, db.n_segments());
            const Kernels& kern = active_kernels();
            StepResult r;
            {
                py::gil_scoped_release release;
                StepEngine engine(kern, db, threads <= 0 ? default_threads() : threads);
                r = engine.step(prev.data(), q.data, q.rows, opt);
            }
            return step_result_dict(r);
        },
        py::arg("pose").noconvert(), py::arg("audio").noconvert(), py::arg("seg_start").noconvert(),
        py::arg("seg_len").noconvert(), py::arg("prev").noconvert(), py::arg("query").noconvert(),
        py::arg("k"), py::arg("preselect"), py::arg("allowed").noconvert().none(true),
        py::arg("exclude").noconvert().none(true), py::arg("threads") = 0,
        py::arg("pose_f16").noconvert().none(true) = py::none(), py::arg("pose_proj").none(true) = py::none(),
        "One rank-sum step (use gesturedb.search.rank_sum_step, which validates).");

    m.def(
        "preselect",
        [](const F32& pose, const F32& audio, const I64& seg_start, const I64& seg_len, const F32& prev,
           const F32& query, const std::string& preselect, const std::optional<U64>& allowed,
           const std::optional<Bool>& exclude, int threads, const std::optional<U16>& pose_f16,
           const std::optional<py::tuple>& pose_proj, bool other) {
            const Database db = make_db(pose, audio, seg_start, seg_len, pose_f16, pose_proj);
            check_vector(prev, db.pose.cols, "prev_pose");
            const Span2<const float> q = span2(query, "query_audio");
            if (q.cols != db.audio.cols || q.rows < 1)
                throw std::invalid_argument("query_audio: expected (n >= 1, " +
                                            std::to_string(db.audio.cols) + "); got " + shape_str(query));
            StepOptions opt;
            opt.preselect = parse_preselect(preselect);
            opt.allowed = make_allowed(allowed, db, false).at(0);
            opt.exclude = exclude_ptr(exclude, db.n_segments());
            opt.other = other;
            const Kernels& kern = active_kernels();
            const int64_t M = db.n_segments();
            py::array_t<int64_t> s(M);
            py::array_t<float> dp(M);
            py::array_t<double> da(M);
            int64_t* ps = s.mutable_data();
            float* pdp = dp.mutable_data();
            double* pda = da.mutable_data();
            {
                py::gil_scoped_release release;
                StepEngine engine(kern, db, threads <= 0 ? default_threads() : threads);
                engine.preselect(prev.data(), q.data, q.rows, opt, ps, pdp, pda);
            }
            return py::make_tuple(s, dp, da);
        },
        py::arg("pose").noconvert(), py::arg("audio").noconvert(), py::arg("seg_start").noconvert(),
        py::arg("seg_len").noconvert(), py::arg("prev").noconvert(), py::arg("query").noconvert(),
        py::arg("preselect"), py::arg("allowed").noconvert().none(true),
        py::arg("exclude").noconvert().none(true), py::arg("threads") = 0,
        py::arg("pose_f16").noconvert().none(true) = py::none(), py::arg("pose_proj").none(true) = py::none(),
        py::arg("other") = true,
        "Pre-selection table of one step (use gesturedb.tables.preselect_table, which validates).");

    m.def(
        "forward_kinematics",
        [](const F64& mats, const F64& root, const I64& parents, const F64& offsets, bool want_worlds) {
            // (F, J, 3, 3), (F, 3), (J,), (J, 3): checked here too, a wrong shape would read out of bounds
            require_ndim(mats, 4, "mats");
            const int64_t F = mats.shape(0), J = mats.shape(1);
            if (J < 1 || mats.shape(2) != 3 || mats.shape(3) != 3)
                throw std::invalid_argument("mats: expected (F, J >= 1, 3, 3); got " + shape_str(mats));
            const int64_t* par = check_chain(root, parents, offsets, F, J);
            py::array_t<double> pos({F, J, int64_t(3)});
            py::array_t<double> worlds(want_worlds ? std::vector<int64_t>{F, J, 3, 3}
                                                   : std::vector<int64_t>{0});
            double* pw = want_worlds ? worlds.mutable_data() : nullptr;
            double* pp = pos.mutable_data();
            {
                py::gil_scoped_release release;
                forward_kinematics(mats.data(), root.data(), par, offsets.data(), F, J, pp, pw);
            }
            return py::make_tuple(pos, want_worlds ? py::object(worlds) : py::object(py::none()));
        },
        py::arg("mats").noconvert(), py::arg("root").noconvert(), py::arg("parents").noconvert(),
        py::arg("offsets").noconvert(), py::arg("want_worlds"),
        "Joint positions (F, J, 3) and world matrices (F, J, 3, 3) or None (use gesturedb.motion.Motion).");

    m.def(
        "forward_kinematics_quat",
        [](const F64& quats, const F64& root, const I64& parents, const F64& offsets, bool want_rotations) {
            // (F, J, 4), (F, 3), (J,), (J, 3): checked here too, a wrong shape would read out of bounds
            require_ndim(quats, 3, "quats");
            const int64_t F = quats.shape(0), J = quats.shape(1);
            if (J < 1 || quats.shape(2) != 4)
                throw std::invalid_argument("quats: expected (F, J >= 1, 4); got " + shape_str(quats));
            const int64_t* par = check_chain(root, parents, offsets, F, J);
            py::array_t<double> pos({F, J, int64_t(3)});
            py::array_t<double> grot(want_rotations ? std::vector<int64_t>{F, J, 4}
                                                    : std::vector<int64_t>{0});
            double* pg = want_rotations ? grot.mutable_data() : nullptr;
            double* pp = pos.mutable_data();
            {
                py::gil_scoped_release release;
                forward_kinematics_quat(quats.data(), root.data(), par, offsets.data(), F, J, pp, pg);
            }
            return py::make_tuple(pos, want_rotations ? py::object(grot) : py::object(py::none()));
        },
        py::arg("quats").noconvert(), py::arg("root").noconvert(), py::arg("parents").noconvert(),
        py::arg("offsets").noconvert(), py::arg("want_rotations"),
        "Joint positions (F, J, 3) and world rotations (F, J, 4) or None from local quaternions (use "
        "gesturedb.motion.Motion).");

    m.def(
        "apply_quintic_rotation_offsets",
        [](const F64& x0, const F64& v0, const F64& a0, const F64& decay, const F64& t, const F64& rot) {
            // (J, 3) x3, (J,), (n,), (n, J, 4): checked here too, a wrong shape would read out of bounds
            require_ndim(rot, 3, "rot");
            const int64_t n = rot.shape(0), J = rot.shape(1);
            if (rot.shape(2) != 4)
                throw std::invalid_argument("rot: expected (n, J, 4); got " + shape_str(rot));
            for (const auto& [name, a] :
                 {std::pair<const char*, const F64*>{"x0", &x0}, {"v0", &v0}, {"a0", &a0}})
                if (a->ndim() != 2 || a->shape(0) != J || a->shape(1) != 3)
                    throw std::invalid_argument(std::string(name) + ": expected (" + std::to_string(J) +
                                                ", 3); got " + shape_str(*a));
            if (decay.ndim() != 1 || decay.shape(0) != J)
                throw std::invalid_argument("decay: expected (" + std::to_string(J) + ",); got " +
                                            shape_str(decay));
            if (t.ndim() != 1 || t.shape(0) != n)
                throw std::invalid_argument("t: expected (" + std::to_string(n) + ",); got " + shape_str(t));
            py::array_t<double> out({n, J, int64_t(4)});
            double* po = out.mutable_data();
            {
                py::gil_scoped_release release;
                apply_quintic_rotation_offsets(x0.data(), v0.data(), a0.data(), decay.data(), t.data(), n, J,
                                               rot.data(), po);
            }
            return out;
        },
        py::arg("x0").noconvert(), py::arg("v0").noconvert(), py::arg("a0").noconvert(),
        py::arg("decay").noconvert(), py::arg("t").noconvert(), py::arg("rot").noconvert(),
        "exp(quintic offsets at t) * rot, (n, J, 4) (use "
        "gesturedb.synth.seams.apply_quintic_rotation_offsets, which validates).");

    m.def(
        "add_quintic_offsets",
        [](const F64& x0, const F64& v0, const F64& a0, double decay, const F64& t, const F64& base) {
            // (k,) x3, (n,), (n, k): checked here too, a wrong shape would read out of bounds
            require_ndim(base, 2, "base");
            const int64_t n = base.shape(0), k = base.shape(1);
            for (const auto& [name, a] :
                 {std::pair<const char*, const F64*>{"x0", &x0}, {"v0", &v0}, {"a0", &a0}})
                if (a->ndim() != 1 || a->shape(0) != k)
                    throw std::invalid_argument(std::string(name) + ": expected (" + std::to_string(k) +
                                                ",); got " + shape_str(*a));
            if (t.ndim() != 1 || t.shape(0) != n)
                throw std::invalid_argument("t: expected (" + std::to_string(n) + ",); got " + shape_str(t));
            py::array_t<double> out({n, k});
            add_quintic_offsets(x0.data(), v0.data(), a0.data(), decay, t.data(), n, k, base.data(),
                                out.mutable_data());
            return out;
        },
        py::arg("x0").noconvert(), py::arg("v0").noconvert(), py::arg("a0").noconvert(), py::arg("decay"),
        py::arg("t").noconvert(), py::arg("base").noconvert(),
        "base + the quintic offsets at t, (n, k) (a seam's root: gesturedb.synth.assemble._Offset.apply).");

    // these run microseconds on a few frames: the GIL stays held (releasing it would cost as much)
    m.def(
        "place_frames",
        [](const F64& q, const F64& rot, const F64& root, const F64& src, std::optional<F64> dst,
           bool zero_y) {
            // (n or 1, 4), (n, J, 4), (n, 3), (n or 1, 3), (3,) or None: checked here too, a wrong shape
            // would read out of bounds
            require_ndim(rot, 3, "rot");
            const int64_t n = rot.shape(0), J = rot.shape(1);
            if (rot.shape(2) != 4 || J < 1)
                throw std::invalid_argument("rot: expected (n, J >= 1, 4); got " + shape_str(rot));
            if (q.ndim() != 2 || (q.shape(0) != n && q.shape(0) != 1) || q.shape(1) != 4)
                throw std::invalid_argument("q: expected (" + std::to_string(n) + " or 1, 4); got " +
                                            shape_str(q));
            if (root.ndim() != 2 || root.shape(0) != n || root.shape(1) != 3)
                throw std::invalid_argument("root: expected (" + std::to_string(n) + ", 3); got " +
                                            shape_str(root));
            if (src.ndim() != 2 || (src.shape(0) != n && src.shape(0) != 1) || src.shape(1) != 3)
                throw std::invalid_argument("src: expected (" + std::to_string(n) + " or 1, 3); got " +
                                            shape_str(src));
            if (dst && (dst->ndim() != 1 || dst->shape(0) != 3))
                throw std::invalid_argument("dst: expected (3,); got " + shape_str(*dst));
            py::array_t<double> out_rot({n, J, int64_t(4)}), out_root({n, int64_t(3)});
            place_frames(q.data(), q.shape(0) == n && n != 1, rot.data(), n, J, root.data(), src.data(),
                         src.shape(0) == n && n != 1, zero_y, dst ? dst->data() : nullptr,
                         out_rot.mutable_data(), out_root.mutable_data());
            return py::make_tuple(out_rot, out_root);
        },
        py::arg("q").noconvert(), py::arg("rot").noconvert(), py::arg("root").noconvert(),
        py::arg("src").noconvert(), py::arg("dst").noconvert(), py::arg("zero_y"),
        "Frames (n, J, 4), (n, 3) turned by q about their source origin (use "
        "gesturedb.synth.assemble._place).");

    m.def(
        "pull_root",
        [](const F64& yaw, const F64& dyaw, const F64& dx, int64_t first, double kh, double kp, double h_prev,
           double y_prev0, double y_prev1) {
            // (T,), (T - first,), (T - first, 2): checked here too, a wrong shape would read out of bounds
            require_ndim(yaw, 1, "yaw");
            const int64_t T = yaw.shape(0);
            if (first != 0 && first != 1)
                throw std::invalid_argument("first: expected 0 or 1; got " + std::to_string(first));
            if (dyaw.ndim() != 1 || dyaw.shape(0) != T - first)
                throw std::invalid_argument("dyaw: expected (" + std::to_string(T - first) + ",); got " +
                                            shape_str(dyaw));
            if (dx.ndim() != 2 || dx.shape(0) != T - first || dx.shape(1) != 2)
                throw std::invalid_argument("dx: expected (" + std::to_string(T - first) + ", 2); got " +
                                            shape_str(dx));
            py::array_t<double> h({T}), y({T, int64_t(2)});
            double *ph = h.mutable_data(), *py_ = y.mutable_data();
            if (first == 1 && T > 0) {
                ph[0] = h_prev;
                py_[0] = y_prev0;
                py_[1] = y_prev1;
            }
            pull_root(yaw.data(), dyaw.data(), dx.data(), T, first, kh, kp, h_prev, y_prev0, y_prev1, ph,
                      py_);
            return py::make_tuple(h, y);
        },
        py::arg("yaw").noconvert(), py::arg("dyaw").noconvert(), py::arg("dx").noconvert(), py::arg("first"),
        py::arg("kh"), py::arg("kp"), py::arg("h_prev"), py::arg("y_prev0"), py::arg("y_prev1"),
        "Pulled heading (T,) and horizontal root (T, 2) (use gesturedb.synth.assemble._Pull).");

    m.def(
        "seam_offset",
        [](const F64& old_rot, const F64& new_rot, const F64& old_root, const F64& new_root, double fps,
           std::optional<F64> accel_rot, double accel_root, double decay_s, double max_decay_s) {
            // (3, J, 4) x2, (3, 3) x2, (J,) or None: checked here too, a wrong shape would read out of bounds
            require_ndim(old_rot, 3, "old_rot");
            const int64_t J = old_rot.shape(1);
            if (old_rot.shape(0) != 3 || old_rot.shape(2) != 4)
                throw std::invalid_argument("old_rot: expected (3, J, 4); got " + shape_str(old_rot));
            if (new_rot.ndim() != 3 || new_rot.shape(0) != 3 || new_rot.shape(1) != J ||
                new_rot.shape(2) != 4)
                throw std::invalid_argument("new_rot: expected (3, " + std::to_string(J) + ", 4); got " +
                                            shape_str(new_rot));
            for (const auto& [name, a] :
                 {std::pair<const char*, const F64*>{"old_root", &old_root}, {"new_root", &new_root}})
                if (a->ndim() != 2 || a->shape(0) != 3 || a->shape(1) != 3)
                    throw std::invalid_argument(std::string(name) + ": expected (3, 3); got " +
                                                shape_str(*a));
            if (accel_rot && (accel_rot->ndim() != 1 || accel_rot->shape(0) != J))
                throw std::invalid_argument("accel_rot: expected (" + std::to_string(J) + ",); got " +
                                            shape_str(*accel_rot));
            py::array_t<double> rot_der({int64_t(3), J, int64_t(3)}), root_der({int64_t(3), int64_t(3)}),
                decay_rot({J});
            double decay_root = 0.0;
            seam_offset(old_rot.data(), new_rot.data(), old_root.data(), new_root.data(), J, fps,
                        accel_rot.has_value(), accel_rot ? accel_rot->data() : nullptr, accel_root, decay_s,
                        max_decay_s, rot_der.mutable_data(), root_der.mutable_data(),
                        decay_rot.mutable_data(), &decay_root);
            return py::make_tuple(rot_der, root_der, decay_rot, decay_root);
        },
        py::arg("old_rot").noconvert(), py::arg("new_rot").noconvert(), py::arg("old_root").noconvert(),
        py::arg("new_root").noconvert(), py::arg("fps"), py::arg("accel_rot").noconvert(),
        py::arg("accel_root"), py::arg("decay_s"), py::arg("max_decay_s"),
        "A seam's offsets (x0, v0, a0) of the joints (3, J, 3) and the root (3, 3) and their decays (J,), s "
        "(use gesturedb.synth.assemble._seam_offset).");

    m.def(
        "two_bone_ik",
        [](const F64& rotations, const F64& global_rot, const F64& positions, const F64& target, int64_t hip,
           int64_t knee, int64_t ankle) {
            // (n, J, 4), (n, J, 4), (n, J, 3), (n, 3): checked here too, a wrong shape or joint would read
            // out of bounds
            require_ndim(rotations, 3, "rotations");
            const int64_t n = rotations.shape(0), J = rotations.shape(1);
            if (rotations.shape(2) != 4)
                throw std::invalid_argument("rotations: expected (n, J, 4); got " + shape_str(rotations));
            const std::string nj = "(" + std::to_string(n) + ", " + std::to_string(J);
            if (global_rot.ndim() != 3 || global_rot.shape(0) != n || global_rot.shape(1) != J ||
                global_rot.shape(2) != 4)
                throw std::invalid_argument("global_rot: expected " + nj + ", 4); got " +
                                            shape_str(global_rot));
            if (positions.ndim() != 3 || positions.shape(0) != n || positions.shape(1) != J ||
                positions.shape(2) != 3)
                throw std::invalid_argument("positions: expected " + nj + ", 3); got " +
                                            shape_str(positions));
            if (target.ndim() != 2 || target.shape(0) != n || target.shape(1) != 3)
                throw std::invalid_argument("target: expected (" + std::to_string(n) + ", 3); got " +
                                            shape_str(target));
            for (const auto& [name, j] : {std::pair{"hip", hip}, {"knee", knee}, {"ankle", ankle}})
                if (j < 0 || j >= J)
                    throw std::invalid_argument(std::string(name) + ": expected a joint in [0, " +
                                                std::to_string(J) + "); got " + std::to_string(j));
            // the result is a copy with the three joints changed (the caller's rotations stay)
            py::array_t<double> out({n, J, int64_t(4)});
            double* po = out.mutable_data();
            std::memcpy(po, rotations.data(), sizeof(double) * size_t(n) * size_t(J) * 4);
            {
                py::gil_scoped_release release;
                two_bone_ik(po, global_rot.data(), positions.data(), target.data(), n, J, hip, knee, ankle);
            }
            return out;
        },
        py::arg("rotations").noconvert(), py::arg("global_rot").noconvert(), py::arg("positions").noconvert(),
        py::arg("target").noconvert(), py::arg("hip"), py::arg("knee"), py::arg("ankle"),
        "Local rotations (n, J, 4) with hip, knee and ankle turned so the ankle reaches target (use "
        "gesturedb.synth.contacts.two_bone_ik, which validates).");

    m.def(
        "audio_distances",
        [](const F32& pose, const F32& audio, const I64& seg_start, const I64& seg_len, const I64& starts,
           const F32& query) {
            const Database db = make_db(pose, audio, seg_start, seg_len);
            const int64_t M = db.n_segments();
            check_vector(starts, M, "starts");
            const Span2<const float> q = span2(query, "query_audio");
            if (q.cols != db.audio.cols || q.rows < 1)
                throw std::invalid_argument("query_audio: expected (n >= 1, " +
                                            std::to_string(db.audio.cols) + "); got " + shape_str(query));
            const int64_t* ps = starts.data();
            check_starts(db, ps, q.rows);
            py::array_t<double> da(M);
            double* pda = da.mutable_data();
            {
                py::gil_scoped_release release;
                audio_distances(active_kernels(), db, ps, q.data, q.rows, pda);
            }
            return da;
        },
        py::arg("pose").noconvert(), py::arg("audio").noconvert(), py::arg("seg_start").noconvert(),
        py::arg("seg_len").noconvert(), py::arg("starts").noconvert(), py::arg("query").noconvert(),
        "Audio distance of each segment's given start (use gesturedb.tables.audio_distances, which "
        "validates).");

    m.def(
        "gather_windows",
        [](const F32& pose, const F32& audio, const I64& seg_start, const I64& seg_len, const I64& starts,
           int64_t n) {
            const Database db = make_db(pose, audio, seg_start, seg_len);
            const int64_t M = db.n_segments();
            check_vector(starts, M, "starts");
            if (n < 1) throw std::invalid_argument("n: expected >= 1; got " + std::to_string(n));
            check_starts(db, starts.data(), n);
            py::array_t<float> out({M, n, db.audio.cols});
            float* po = out.mutable_data();
            {
                py::gil_scoped_release release;
                gather_windows(db, starts.data(), n, po);
            }
            return out;
        },
        py::arg("pose").noconvert(), py::arg("audio").noconvert(), py::arg("seg_start").noconvert(),
        py::arg("seg_len").noconvert(), py::arg("starts").noconvert(), py::arg("n"),
        "Each segment's candidate window (M, n, Da), zeros where starts is -1 (use "
        "gesturedb.tables.gather_windows, which validates).");

    m.def(
        "window_distances",
        [](const F32& windows, const I64& starts, const F32& query) {
            require_ndim(windows, 3, "windows");
            const int64_t M = windows.shape(0);
            check_vector(starts, M, "starts");
            const Span2<const float> q = span2(query, "query_audio");
            if (q.rows != windows.shape(1) || q.cols != windows.shape(2))
                throw std::invalid_argument("query_audio: expected (" + std::to_string(windows.shape(1)) +
                                            ", " + std::to_string(windows.shape(2)) +
                                            ") as the windows; got " + shape_str(query));
            py::array_t<double> da(M);
            double* pda = da.mutable_data();
            {
                py::gil_scoped_release release;
                window_distances(active_kernels(), windows.data(), starts.data(), M, q.rows * q.cols, q.data,
                                 pda);
            }
            return da;
        },
        py::arg("windows").noconvert(), py::arg("starts").noconvert(), py::arg("query").noconvert(),
        "audio_distances over windows from gather_windows (use gesturedb.tables.window_distances, which "
        "validates).");

    m.def(
        "rank_table",
        [](const I64& start, const F32& pose_dist, const F64& audio_dist, int64_t k) {
            require_ndim(start, 1, "starts");
            const int64_t M = start.shape(0);
            check_vector(pose_dist, M, "pose_dist");
            if (audio_dist.ndim() != 1 || audio_dist.shape(0) != M)
                throw std::invalid_argument("audio_dist: expected (" + std::to_string(M) + ",); got " +
                                            shape_str(audio_dist));
            TableRank r;
            {
                py::gil_scoped_release release;
                r = rank_table(start.data(), pose_dist.data(), audio_dist.data(), M, k);
            }
            return py::make_tuple(r.segment, r.pose_rank, r.audio_rank, r.n_candidates);
        },
        py::arg("starts").noconvert(), py::arg("pose_dist").noconvert(), py::arg("audio_dist").noconvert(),
        py::arg("k"), "Ranks over a pre-selection table (use gesturedb.search.rank_table).");

    m.def(
        "table_top_lists",
        [](const I64& start, const F32& pose_dist, const F64& audio_dist, int64_t n) {
            require_ndim(start, 2, "starts");
            const int64_t Q = start.shape(0), M = start.shape(1);
            auto same_shape = [&](const py::array& arr, const char* name) {
                if (arr.ndim() != 2 || arr.shape(0) != Q || arr.shape(1) != M)
                    throw std::invalid_argument(std::string(name) + ": expected (" + std::to_string(Q) +
                                                ", " + std::to_string(M) + "); got " + shape_str(arr));
            };
            same_shape(pose_dist, "pose_dist");
            same_shape(audio_dist, "audio_dist");
            if (n < 1) throw std::invalid_argument("n: expected >= 1; got " + std::to_string(n));
            py::array_t<int32_t> by_pose({Q, n}), by_audio({Q, n});
            py::array_t<int64_t> n_cand(Q);
            {
                py::gil_scoped_release release;
                table_top_lists(start.data(), pose_dist.data(), audio_dist.data(), Q, M, n,
                                by_pose.mutable_data(), by_audio.mutable_data(), n_cand.mutable_data());
            }
            return py::make_tuple(n_cand, by_pose, by_audio);
        },
        py::arg("starts").noconvert(), py::arg("pose_dist").noconvert(), py::arg("audio_dist").noconvert(),
        py::arg("n"), "Top lists of pre-selection tables (use gesturedb.tables.top_lists).");

    m.def(
        "search",
        [](const F32& pose, const F32& audio, const I64& seg_start, const I64& seg_len, const F32& query,
           const F32& init_pose, int64_t window, int64_t k, const std::string& preselect,
           const std::optional<U64>& allowed, const std::optional<Bool>& exclude, int threads,
           const std::optional<U16>& pose_f16, const std::optional<py::tuple>& pose_proj) {
            const Database db = make_db(pose, audio, seg_start, seg_len, pose_f16, pose_proj);
            check_vector(init_pose, db.pose.cols, "init_pose");
            const Span2<const float> q = span2(query, "query_audio");
            if (window < 1) throw std::invalid_argument("step: expected >= 1; got " + std::to_string(window));
            const int64_t S = q.rows >= 1 ? (q.rows + window - 1) / window : 0;
            const AllowedSchedule sched = make_allowed(allowed, db, true);
            const bool* ex = exclude_ptr(exclude, db.n_segments());
            const Preselect pre = parse_preselect(preselect);
            const Kernels& kern = active_kernels();
            SearchArrays out(S);
            SearchOutput view = out.view();
            int64_t failed;
            {
                py::gil_scoped_release release;
                failed =
                    rank_sum_search(kern, db, q, init_pose.data(), window, k, pre, sched, ex, view, threads);
            }
            return py::make_tuple(out.to_dict(), failed);
        },
        py::arg("pose").noconvert(), py::arg("audio").noconvert(), py::arg("seg_start").noconvert(),
        py::arg("seg_len").noconvert(), py::arg("query").noconvert(), py::arg("init_pose").noconvert(),
        py::arg("window"), py::arg("k"), py::arg("preselect"), py::arg("allowed").noconvert().none(true),
        py::arg("exclude").noconvert().none(true), py::arg("threads") = 0,
        py::arg("pose_f16").noconvert().none(true) = py::none(), py::arg("pose_proj").none(true) = py::none(),
        "A whole search -> (dict of (S,) arrays, failed step or -1) "
        "(use gesturedb.search.rank_sum_search, which validates).");

    // A BatchPlan and the arrays its Database points into: holding them here
    // keeps them alive (and unresizable) as long as the plan.
    struct PyBatchPlan {
        F32 pose, audio;
        I64 seg_start, seg_len;
        std::optional<U16> pose_f16;
        std::optional<py::tuple> pose_proj;
        Database db;
        std::unique_ptr<BatchPlan> plan;
    };
    py::class_<PyBatchPlan>(m, "BatchPlan",
                            "Pre-selection tables of many queries, step after step, on one database "
                            "(use gesturedb.tables.PreselectBatch, which validates).")
        .def(py::init([](const F32& pose, const F32& audio, const I64& seg_start, const I64& seg_len,
                         const std::string& preselect, const std::optional<U16>& pose_f16,
                         const std::optional<py::tuple>& pose_proj) {
                 auto p = std::make_unique<PyBatchPlan>(
                     PyBatchPlan{pose, audio, seg_start, seg_len, pose_f16, pose_proj, {}, {}});
                 p->db = make_db(p->pose, p->audio, p->seg_start, p->seg_len, p->pose_f16, p->pose_proj);
                 p->plan.reset(new BatchPlan(active_kernels(), p->db, parse_preselect(preselect)));
                 return p;
             }),
             py::arg("pose").noconvert(), py::arg("audio").noconvert(), py::arg("seg_start").noconvert(),
             py::arg("seg_len").noconvert(), py::arg("preselect"),
             py::arg("pose_f16").noconvert().none(true) = py::none(),
             py::arg("pose_proj").none(true) = py::none())
        .def(
            "tables",
            [](PyBatchPlan& p, const F32& prevs, const F32& windows, const std::optional<U64>& allowed,
               const std::optional<Bool>& exclude, int threads, const std::string& method, bool other) {
                const Database& db = p.db;
                const int64_t M = db.n_segments();
                const Span2<const float> pv = span2(prevs, "prev_poses");
                const int64_t Q = pv.rows;
                if (pv.cols != db.pose.cols)
                    throw std::invalid_argument("prev_poses: expected (Q, " + std::to_string(db.pose.cols) +
                                                "); got " + shape_str(prevs));
                if (windows.ndim() != 3 || windows.shape(0) != Q || windows.shape(1) < 1 ||
                    windows.shape(2) != db.audio.cols)
                    throw std::invalid_argument("query_windows: expected (" + std::to_string(Q) +
                                                ", n >= 1, " + std::to_string(db.audio.cols) + "); got " +
                                                shape_str(windows));
                const BatchMethod bm = parse_method(method);
                // one bitset for every query, or (Q, words): each query's own
                const bool per_query = allowed && allowed->ndim() == 2;
                const AllowedSchedule sched =
                    per_query ? AllowedSchedule{} : make_allowed(allowed, db, false);
                const BatchExclude ex = batch_exclude(exclude, Q, M);
                const int64_t n = windows.shape(1), Da = db.audio.cols;
                py::array_t<int64_t> s({Q, M});
                py::array_t<float> dp({Q, M});
                py::array_t<double> da({Q, M});
                std::vector<BatchQuery> batch(Q);
                for (int64_t i = 0; i < Q; ++i) {
                    batch[i].audio = Span2<const float>{windows.data() + i * n * Da, n, Da};
                    batch[i].init_pose = pv.row(i);
                    batch[i].k = 1;
                    batch[i].exclude = ex.row(i);
                    batch[i].table_s = s.mutable_data() + i * M;
                    batch[i].table_dp = dp.mutable_data() + i * M;
                    batch[i].table_da = da.mutable_data() + i * M;
                    batch[i].table_other = other;
                }
                if (per_query) set_query_allowed(batch, *allowed, db);
                {
                    py::gil_scoped_release release;
                    p.plan->preselect(batch, sched, threads, bm);
                }
                return py::make_tuple(s, dp, da);
            },
            py::arg("prev_poses").noconvert(), py::arg("query_windows").noconvert(),
            py::arg("allowed").noconvert().none(true), py::arg("exclude").noconvert().none(true),
            py::arg("threads") = 0, py::arg("method") = "auto", py::arg("other") = true,
            "Pre-selection tables of one step for many queries -> (starts, pose_dist, audio_dist), each (Q, "
            "M); other=False leaves the other distance 0.")
        .def_property_readonly(
            "n_setups", [](const PyBatchPlan& p) { return p.plan->n_setups(); },
            "Window lengths whose blocked set-up the plan keeps.");

    m.def(
        "search_batch",
        [](const F32& pose, const F32& audio, const I64& seg_start, const I64& seg_len,
           const std::vector<F32>& queries, const F32& init_poses, int64_t window, const I64& k,
           const std::string& preselect, const std::optional<U64>& allowed,
           const std::optional<Bool>& exclude, int threads, const std::string& method,
           const std::optional<U16>& pose_f16, const std::optional<py::tuple>& pose_proj,
           const std::optional<U64>& query_allowed) {
            const Database db = make_db(pose, audio, seg_start, seg_len, pose_f16, pose_proj);
            const int64_t Q = int64_t(queries.size());
            const BatchMethod bm = parse_method(method);
            const Span2<const float> init = span2(init_poses, "init_poses");
            if (init.rows != Q || init.cols != db.pose.cols)
                throw std::invalid_argument("init_poses: expected (" + std::to_string(Q) + ", " +
                                            std::to_string(db.pose.cols) + "); got " + shape_str(init_poses));
            require_ndim(k, 1, "k");
            if (k.shape(0) != Q)
                throw std::invalid_argument("k: expected " + std::to_string(Q) + " values; got " +
                                            std::to_string(k.shape(0)));
            if (window < 1) throw std::invalid_argument("step: expected >= 1; got " + std::to_string(window));
            const AllowedSchedule sched = make_allowed(allowed, db, true);
            const Preselect pre = parse_preselect(preselect);
            const int64_t M = db.n_segments();
            const BatchExclude ex = batch_exclude(exclude, Q, M);
            std::vector<BatchQuery> batch(Q);
            I64 offsets(Q + 1);
            int64_t* off = offsets.mutable_data();
            off[0] = 0;
            for (int64_t i = 0; i < Q; ++i) {
                batch[i].audio = span2(queries[i], "queries[i]");
                const int64_t T = batch[i].audio.rows;
                off[i + 1] = off[i] + (T >= 1 ? (T + window - 1) / window : 0);
            }
            SearchArrays out(off[Q]);
            const int64_t* kp = k.data();
            for (int64_t i = 0; i < Q; ++i) {
                batch[i].init_pose = init.row(i);
                batch[i].k = kp[i];
                batch[i].exclude = ex.row(i);
                batch[i].out = out.view(off[i]);
            }
            if (query_allowed) {
                if (allowed)
                    throw std::invalid_argument("allowed: expected either it or query_allowed, not both");
                set_query_allowed(batch, *query_allowed, db);
            }
            const Kernels& kern = active_kernels();
            I64 failed(Q);
            {
                py::gil_scoped_release release;
                rank_sum_search_batch(kern, db, batch, window, pre, sched, threads, bm);
            }
            int64_t* f = failed.mutable_data();
            for (int64_t i = 0; i < Q; ++i) f[i] = batch[i].failed_step;
            return py::make_tuple(out.to_dict(), offsets, failed);
        },
        py::arg("pose").noconvert(), py::arg("audio").noconvert(), py::arg("seg_start").noconvert(),
        py::arg("seg_len").noconvert(), py::arg("queries").noconvert(), py::arg("init_poses").noconvert(),
        py::arg("window"), py::arg("k").noconvert(), py::arg("preselect"),
        py::arg("allowed").noconvert().none(true), py::arg("exclude").noconvert().none(true),
        py::arg("threads") = 0, py::arg("method") = "auto",
        py::arg("pose_f16").noconvert().none(true) = py::none(), py::arg("pose_proj").none(true) = py::none(),
        py::arg("query_allowed").noconvert().none(true) = py::none(),
        "Many searches -> (dict of concatenated arrays, offsets (Q+1,), failed step per query) "
        "(use gesturedb.search.rank_sum_search_batch, which validates).");
}
