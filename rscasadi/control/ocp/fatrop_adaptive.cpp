/* fatrop with IPOPT's adaptive barrier rule (free mode: the quality-function oracle; fixed mode:
   the monotone rule as a fallback, with IPOPT's filter of (objective, infeasibility) deciding
   between them), assembled from the parts libfatrop exports; the C functions at the bottom take
   the place of fatrop's C interface for fatrop_direct.c (rsq_* = fatrop_ocp_c_*).

   Why: fatrop's own rule is monotone and takes 20 iterations on problem (b) where IPOPT's
   adaptive rule takes 15 (README, "Why not 5x").  References: Nocedal, Waechter & Waltz,
   "Adaptive barrier update strategies for nonlinear interior methods", SIAM J. Optim. 19 (2009),
   sections 3-4 (the quality function, its golden-section search, the globalisation); IPOPT's
   AdaptiveMuUpdate and QualityFunctionMuOracle with their default options (sigma in
   [1e-6, 100], 2-norm squared, no centrality term, 8 section steps, sigma tolerance 1e-2).

   The search direction is affine in mu: fatrop's right-hand side depends on mu only through the
   complementarity rows (z s - mu).  So per iteration one factorisation and two solves give the
   whole family d(mu) = d_aff + mu d_1, where d_aff solves with mu = 0 and d_1 with the mu-
   derivative of the right-hand side; the oracle chooses mu on it and the step is d(mu), exactly
   the solve at that mu (one back-substitution more than the monotone rule, no refactorisation). */
#include <fatrop/common/options.hpp>
#include <fatrop/common/printing.hpp>
#include <fatrop/ip_algorithm/ip_alg_builder.hpp>
#include <fatrop/ip_algorithm/ip_algorithm.hpp>
#include <fatrop/ip_algorithm/ip_data.hpp>
#include <fatrop/ip_algorithm/ip_iterate.hpp>
#include <fatrop/ip_algorithm/ip_linesearch.hpp>
#include <fatrop/ip_algorithm/ip_mu_update.hpp>
#include <fatrop/ip_algorithm/ip_search_dir.hpp>
#include <fatrop/ip_algorithm/ip_convergence_check.hpp>
#include <fatrop/ip_algorithm/ip_eq_mult_initializer.hpp>
#include <fatrop/ip_algorithm/ip_initializer.hpp>
#include <fatrop/ip_algorithm/ip_iteration_output.hpp>
#include <fatrop/linear_algebra/linear_solver.hpp>
#include <fatrop/ocp/OCPCInterfaceInternal.hpp>
#include <fatrop/ocp/hessian.hpp>
#include <fatrop/ocp/jacobian.hpp>
#include <fatrop/ocp/pd_solver_orig.hpp>
#include <fatrop/ocp/pd_system_orig.hpp>
#include <fatrop/ocp/problem_info.hpp>
#include <fatrop/ocp/type.hpp>

#include <algorithm>
#include <cmath>
#include <memory>
#include <string>
#include <utility>
#include <vector>

using namespace fatrop;
typedef PdSolverOrig<OcpType> PdSolver;
typedef LinearSystem<PdSystemType<OcpType>> PdSystem;
typedef IpData<OcpType> Data;
typedef IpIterate<OcpType> Iterate;
typedef IpAlgBuilder<OcpType> Builder;

/* The builder makes every part and keeps them private; its build() always makes the monotone
   update.  The parts we reuse are read through the standard's explicit-instantiation rule (access
   is not checked in an explicit instantiation), so no layout is assumed. */
template <class Tag, typename Tag::type M> struct Reach { friend typename Tag::type get(Tag) { return M; } };
#define REACH(member, T)                                                                          \
    struct member##tag { typedef T Builder::*type; friend type get(member##tag); };               \
    template struct Reach<member##tag, &Builder::member>;
typedef std::shared_ptr<IpLinesearch<PdSolver, OcpType>> LinesearchSp;
REACH(linesearch_, LinesearchSp)
REACH(initializer_, std::shared_ptr<IpInitializerBase>)
REACH(eq_mult_initializer_, std::shared_ptr<IpEqMultInitializerBase>)
REACH(convergence_check_, std::shared_ptr<IpConvergenceCheckBase>)
REACH(iteration_output_, std::shared_ptr<IpIterationOutputBase>)

namespace
{
    /* One factorisation, the affine direction and the direction per unit of mu; or, when the
       oracle is not used (fixed mode), the plain direction at the current mu (fatrop's
       IpSearchDirImpl, with its inertia correction). */
    class AffineSearchDir : public IpSearchDirBase
    {
    public:
        AffineSearchDir(const std::shared_ptr<Data> &data, const std::shared_ptr<PdSolver> &solver)
            : data_(data), solver_(solver)
        {
            const NlpDims &n = data->current_iterate().nlp()->nlp_dims();
            for (int i = 0; i < 2; i++)
            {
                x_[i] = std::make_unique<VecRealAllocated>(n.number_of_tangent_variables);
                s_[i] = std::make_unique<VecRealAllocated>(n.number_of_ineq_constraints);
                g_[i] = std::make_unique<VecRealAllocated>(n.number_of_eq_constraints);
                cl_[i] = std::make_unique<VecRealAllocated>(n.number_of_ineq_constraints);
                cu_[i] = std::make_unique<VecRealAllocated>(n.number_of_ineq_constraints);
            }
        }
        void reset() override { delta_w_last_ = 0.; pending_ = false; }
        void register_options(OptionRegistry &r) override
        {
            r.register_option("delta_w0", &AffineSearchDir::set_delta_w0, this);
            r.register_option("delta_wmin", &AffineSearchDir::set_delta_wmin, this);
            r.register_option("kappa_wmin", &AffineSearchDir::set_kappa_wmin, this);
            r.register_option("kappa_wplus", &AffineSearchDir::set_kappa_wplus, this);
            r.register_option("kappa_wplusem", &AffineSearchDir::set_kappa_wplusem, this);
            r.register_option("kappa_c", &AffineSearchDir::set_kappa_c, this);
            r.register_option("delta_c_stripe", &AffineSearchDir::set_delta_c_stripe, this);
        }
        void set_delta_w0(const Scalar &v) { delta_w0_ = v; }
        void set_delta_wmin(const Scalar &v) { delta_wmin_ = v; }
        void set_kappa_wmin(const Scalar &v) { kappa_wmin_ = v; }
        void set_kappa_wplus(const Scalar &v) { kappa_wplus_ = v; }
        void set_kappa_wplusem(const Scalar &v) { kappa_wplusem_ = v; }
        void set_kappa_c(const Scalar &v) { kappa_c_ = v; }
        void set_delta_c_stripe(const Scalar &v) { delta_c_stripe_ = v; }

        /* a solve the step may use (fatrop's IpSearchDirImpl accepts these) */
        static bool ok(LinsolReturnFlag f)
        {
            return f == LinsolReturnFlag::SUCCESS || f == LinsolReturnFlag::ITREF_MAX_ITER ||
                   f == LinsolReturnFlag::ITREF_INCREASE;
        }
        /* factorise at the current iterate and solve for mu = 0 (slot 0) and d/dmu (slot 1);
           false: the factorisation failed (compute_search_dir then reports it at the current mu) */
        bool affine_and_unit()
        {
            Iterate &it = data_->current_iterate();
            flag_ = factorise(it, 0.);
            pending_ = ok(flag_);
            if (!pending_)
                return false;
            *x_[1] = VecRealScalar(x_[1]->m(), 0.);
            *s_[1] = VecRealScalar(s_[1]->m(), 0.);
            *g_[1] = VecRealScalar(g_[1]->m(), 0.);
            *cl_[1] = if_else(it.lower_bounded(), VecRealScalar(cl_[1]->m(), -1.), VecRealScalar(cl_[1]->m(), 0.));
            *cu_[1] = if_else(it.upper_bounded(), VecRealScalar(cu_[1]->m(), -1.), VecRealScalar(cu_[1]->m(), 0.));
            PdSystem ls = system(it, 1);
            data_->timing_statistics().compute_search_dir.start();
            LinsolReturnFlag f = solver_->solve_in_place_rhs(ls);
            data_->timing_statistics().compute_search_dir.pause();
            if (!ok(f) || !x_[1]->is_finite())
                pending_ = false, flag_ = LinsolReturnFlag::NAN_SOLUTION;
            return pending_;
        }
        /* slot i's step for the slacks and bound multipliers (the oracle's inputs) */
        const VecRealAllocated &ds(int i) const { return *s_[i]; }
        const VecRealAllocated &dzl(int i) const { return *cl_[i]; }
        const VecRealAllocated &dzu(int i) const { return *cu_[i]; }
        void use(Scalar mu) { mu_ = mu; }

        LinsolReturnFlag compute_search_dir() override
        {
            Iterate &it = data_->current_iterate();
            if (pending_)
            {
                pending_ = false;
                it.set_delta_primal_x(*x_[0] + mu_ * *x_[1]);
                it.set_delta_primal_s(*s_[0] + mu_ * *s_[1]);
                it.set_delta_dual_eq(*g_[0] + mu_ * *g_[1]);
                it.set_delta_dual_bounds_l(*cl_[0] + mu_ * *cl_[1]);
                it.set_delta_dual_bounds_u(*cu_[0] + mu_ * *cu_[1]);
                return flag_;
            }
            LinsolReturnFlag f = factorise(it, it.mu());
            if (!ok(f))
                return f;
            it.set_delta_primal_x(*x_[0]);
            it.set_delta_primal_s(*s_[0]);
            it.set_delta_dual_eq(*g_[0]);
            it.set_delta_dual_bounds_l(*cl_[0]);
            it.set_delta_dual_bounds_u(*cu_[0]);
            return f;
        }

    private:
        PdSystem system(Iterate &it, int i)
        {
            return PdSystem(it.info(), it.jacobian(), it.hessian(), it.Dx(), it.De_is_zero(), it.De(),
                            it.delta_lower(), it.delta_upper(), it.dual_bounds_l(), it.dual_bounds_u(),
                            *x_[i], *s_[i], *g_[i], *cl_[i], *cu_[i]);
        }
        /* fatrop's IpSearchDirImpl::compute_search_dir, right-hand side at mu_rhs, into slot 0 */
        LinsolReturnFlag factorise(Iterate &it, Scalar mu_rhs)
        {
            Scalar delta_w = 0., delta_c = 0.;
            bool first_try_delta_w = true;
            while (true)
            {
                *x_[0] = it.dual_infeasibility_x();
                *s_[0] = it.dual_infeasibility_s();
                *g_[0] = it.constr_viol();
                *cl_[0] = it.relaxed_complementarity_l(mu_rhs);
                *cu_[0] = it.relaxed_complementarity_u(mu_rhs);
                it.set_Dx(VecRealScalar(it.Dx().m(), delta_w) + it.primal_damping());
                it.set_De(VecRealScalar(it.De().m(), delta_c));
                it.set_De_is_zero(delta_c == 0.);
                PdSystem ls = system(it, 0);
                data_->timing_statistics().compute_search_dir.start();
                LinsolReturnFlag ret = solver_->solve_in_place(ls);
                data_->timing_statistics().compute_search_dir.pause();
                if (ok(ret))
                {
                    if (delta_w > 0)
                        delta_w_last_ = delta_w;
                    it.search_dir_info().inertia_correction_primal = delta_w;
                    it.search_dir_info().inertia_correction_dual = delta_c;
                    return ret;
                }
                if (ret == LinsolReturnFlag::INDEFINITE)
                {
                    if (first_try_delta_w)
                    {
                        delta_w = delta_w_last_ == 0. ? delta_w0_ : std::max(delta_w_last_ * kappa_wmin_, delta_wmin_);
                        first_try_delta_w = false;
                    }
                    else
                        delta_w = delta_w_last_ == 0. ? kappa_wplusem_ * delta_w : kappa_wplus_ * delta_w;
                }
                else if (ret == LinsolReturnFlag::NOFULL_RANK)
                    delta_c = delta_c_stripe_ * std::pow(it.mu(), kappa_c_);
                else
                    return ret;
            }
        }
        std::shared_ptr<Data> data_;
        std::shared_ptr<PdSolver> solver_;
        std::unique_ptr<VecRealAllocated> x_[2], s_[2], g_[2], cl_[2], cu_[2];
        bool pending_ = false;
        LinsolReturnFlag flag_ = LinsolReturnFlag::SUCCESS;
        Scalar mu_ = 0.;
        Scalar delta_w_last_ = 0., delta_w0_ = 1e-4, delta_wmin_ = 1e-20, kappa_wmin_ = 1. / 3.,
               kappa_wplus_ = 8., kappa_wplusem_ = 100., kappa_c_ = 0.25, delta_c_stripe_ = 1e-6;
    };

    /* IPOPT's adaptive barrier update (AdaptiveMuUpdate, globalisation obj-constr-filter) with
       the quality-function oracle (QualityFunctionMuOracle) */
    class AdaptiveMuUpdate : public IpMuUpdateBase
    {
    public:
        AdaptiveMuUpdate(const std::shared_ptr<Data> &data, const std::shared_ptr<IpLineSearchBase> &linesearch,
                         const std::shared_ptr<AffineSearchDir> &search_dir)
            : data_(data), linesearch_(linesearch), search_dir_(search_dir)
        {
        }
        void reset() override
        {
            data_->current_iterate().set_mu(mu_init_);
            data_->trial_iterate().set_mu(mu_init_);
            free_mode_ = true;
            mu_max_ = -1.;
            filter_.clear();
            history_.clear();
            oracle_calls_ = fixed_iterations_ = 0;
        }
        void register_options(OptionRegistry &r) override
        {
            r.register_option("mu_init", &AdaptiveMuUpdate::set_mu_init, this);
            r.register_option("barrier_tol_factor", &AdaptiveMuUpdate::set_barrier_tol_factor, this);
            r.register_option("mu_linear_decrease_factor", &AdaptiveMuUpdate::set_mu_linear_decrease_factor, this);
            r.register_option("mu_superlinear_decrease_power", &AdaptiveMuUpdate::set_mu_superlinear_decrease_power, this);
            r.register_option("compl_inf_tol", &AdaptiveMuUpdate::set_compl_inf_tol, this);
        }
        void set_mu_init(const Scalar &v) { mu_init_ = v; }
        void set_barrier_tol_factor(const Scalar &v) { barrier_tol_factor_ = v; }
        void set_mu_linear_decrease_factor(const Scalar &v) { mu_linear_decrease_factor_ = v; }
        void set_mu_superlinear_decrease_power(const Scalar &v) { mu_superlinear_decrease_power_ = v; }
        void set_compl_inf_tol(const Scalar &v) { compl_inf_tol_ = v; }
        int oracle_calls() const { return oracle_calls_; }
        int fixed_iterations() const { return fixed_iterations_; }
        const std::vector<Scalar> &history() const { return history_; }

        bool update_barrier_parameter() override
        {
            bool ret = update();
            history_.push_back(data_->current_iterate().mu());
            return ret;
        }

    private:

        bool update()
        {
            Iterate &it = data_->current_iterate();
            if (it.number_of_bounds() == 0)
            {
                set_mu(mu_min());
                return true;
            }
            if (mu_max_ < 0.)
                mu_max_ = mu_max_fact_ * average_complementarity(it);
            bool tiny_step = data_->tiny_step_flag();
            data_->set_tiny_step_flag(false);
            if (!free_mode_)
            {
                if (sufficient_progress(it) && !tiny_step)
                {
                    free_mode_ = true;
                    remember(it);
                }
                else
                {
                    Scalar mu = it.mu();
                    if (it.e_mu(mu) <= barrier_tol_factor_ * mu || tiny_step)
                    {   // the monotone rule, one decrease per iteration
                        Scalar new_mu = std::min(mu_linear_decrease_factor_ * mu, std::pow(mu, mu_superlinear_decrease_power_));
                        set_mu(std::max(new_mu, std::min(data_->tolerance(), compl_inf_tol_) / (barrier_tol_factor_ + 1.)));
                        linesearch_->reset_linesearch();
                    }
                }
            }
            else if (sufficient_progress(it) && !tiny_step)
                remember(it);
            else
            {   // to fixed mode at mu = 0.8 * the average complementarity
                free_mode_ = false;
                set_mu(std::min(std::max(0.8 * average_complementarity(it), mu_min()), mu_max_));
                linesearch_->reset_linesearch();
            }
            if (!free_mode_)
            {
                fixed_iterations_++;
                return true;
            }
            Scalar mu;
            if (!oracle(it, mu))
            {   // the linear system failed: the search direction (at the last mu) says how
                return true;
            }
            oracle_calls_++;
            mu = std::min(std::max(mu, mu_min()), mu_max_);
            set_mu(mu);
            search_dir_->use(mu);
            linesearch_->reset_linesearch();
            return true;
        }
        Scalar mu_min() const { return std::min(1e-11, 0.5 * std::min(data_->tolerance(), compl_inf_tol_)); }
        void set_mu(Scalar mu)
        {
            data_->current_iterate().set_mu(mu);
            data_->trial_iterate().set_mu(mu);
        }
        static Scalar average_complementarity(Iterate &it)
        {
            return (sum(it.complementarity_l()) + sum(it.complementarity_u())) / it.number_of_bounds();
        }
        static const Scalar *raw(const VecRealView &v) { return v.vec().pa + v.ai(); }
        /* IPOPT's filter of (objective, constraint violation) over the points accepted in free mode */
        bool sufficient_progress(Iterate &it)
        {
            Scalar margin = 1e-5 * std::min(1., it.e_mu(0.));
            Scalar f = it.obj_value() + margin, theta = it.constr_viol_inf() + margin;
            for (const auto &e : filter_)
                if (!(f <= e.first || theta <= e.second))
                    return false;
            return true;
        }
        void remember(Iterate &it)
        {
            Scalar f = it.obj_value(), theta = it.constr_viol_inf();
            filter_.erase(std::remove_if(filter_.begin(), filter_.end(),
                                         [&](const std::pair<Scalar, Scalar> &e) { return f <= e.first && theta <= e.second; }),
                          filter_.end());
            filter_.emplace_back(f, theta);
        }

        /* the quality function's inputs at this iterate, per bound (lower ones, then upper ones):
           slack, multiplier, and the slack's and multiplier's steps for mu = 0 and per unit mu
           (the slack's step negated for upper bounds, so that both read as lower bounds) */
        struct Model
        {
            std::vector<Scalar> s, z, ds0, ds1, dz0, dz1;
            Scalar dual2, primal2, tau;
            Index n_dual, n_primal, n_compl;
        };
        /* q(mu): the linearised KKT error after the fraction-to-boundary steps along d(mu) */
        static Scalar quality(const Model &m, Scalar mu)
        {
            const size_t n = m.s.size();
            Scalar ap = 1., ad = 1.;
            for (size_t i = 0; i < n; i++)
            {
                Scalar ds = m.ds0[i] + mu * m.ds1[i], dz = m.dz0[i] + mu * m.dz1[i];
                if (ds < 0)
                    ap = std::min(ap, -m.tau * m.s[i] / ds);
                if (dz < 0)
                    ad = std::min(ad, -m.tau * m.z[i] / dz);
            }
            Scalar compl2 = 0.;
            for (size_t i = 0; i < n; i++)
            {
                Scalar c = (m.s[i] + ap * (m.ds0[i] + mu * m.ds1[i])) * (m.z[i] + ad * (m.dz0[i] + mu * m.dz1[i]));
                compl2 += c * c;
            }
            Scalar q = (1. - ad) * (1. - ad) * m.dual2 / m.n_dual + compl2 / m.n_compl;
            if (m.n_primal > 0)
                q += (1. - ap) * (1. - ap) * m.primal2 / m.n_primal;
            return q;
        }
        Model model(Iterate &it)
        {
            Model m;
            const Index n = it.primal_s().m();
            const Scalar *ds[2] = {raw(search_dir_->ds(0)), raw(search_dir_->ds(1))};
            const Scalar *dzl[2] = {raw(search_dir_->dzl(0)), raw(search_dir_->dzl(1))};
            const Scalar *dzu[2] = {raw(search_dir_->dzu(0)), raw(search_dir_->dzu(1))};
            const VecRealView &sl = it.delta_lower(), &su = it.delta_upper(), &zl = it.dual_bounds_l(),
                              &zu = it.dual_bounds_u();
            for (int upper = 0; upper < 2; upper++)
                for (Index i = 0; i < n; i++)
                {
                    if (!(upper ? it.upper_bounded()[i] : it.lower_bounded()[i]))
                        continue;
                    const Scalar sign = upper ? -1. : 1.;
                    m.s.push_back(upper ? su(i) : sl(i));
                    m.z.push_back(upper ? zu(i) : zl(i));
                    m.ds0.push_back(sign * ds[0][i]);
                    m.ds1.push_back(sign * ds[1][i]);
                    m.dz0.push_back(upper ? dzu[0][i] : dzl[0][i]);
                    m.dz1.push_back(upper ? dzu[1][i] : dzl[1][i]);
                }
            m.dual2 = sumsqr(it.dual_infeasibility_x()) + sumsqr(it.dual_infeasibility_s());
            m.primal2 = sumsqr(it.constr_viol());
            m.n_dual = it.dual_infeasibility_x().m() + n;
            m.n_primal = it.constr_viol().m();
            m.n_compl = it.number_of_bounds();
            m.tau = std::max(0.99, 1. - it.e_mu(0.));
            return m;
        }
        /* QualityFunctionMuOracle::CalculateMu: sigma = mu / average complementarity */
        bool oracle(Iterate &it, Scalar &mu)
        {
            if (!search_dir_->affine_and_unit())
                return false;
            const Model m = model(it);
            const Scalar avg = average_complementarity(it);
            auto q = [&](Scalar sigma) { return quality(m, sigma * avg); };
            const Scalar q1 = q(1.), sigma_1minus = 1. - std::max(1e-4, sigma_tol_), q1minus = q(sigma_1minus);
            Scalar sigma;
            if (q1minus > q1)
            {
                Scalar up = std::min(sigma_max_, mu_max_ / avg), lo = 1.;
                sigma = lo >= up ? up : golden_section(q, up, -100., lo, q1);
            }
            else
            {
                Scalar lo = std::max(sigma_min_, mu_min() / avg), up = std::min(std::max(lo, sigma_1minus), mu_max_ / avg);
                sigma = lo >= up ? lo : golden_section(q, up, q1minus, lo, -100.);
            }
            mu = sigma * avg;
            return true;
        }
        /* QualityFunctionMuOracle::PerformGoldenSection (q < 0: not evaluated yet) */
        template <typename Q> Scalar golden_section(Q &q, Scalar up_in, Scalar q_up, Scalar lo_in, Scalar q_lo)
        {
            const Scalar g = (3. - std::sqrt(5.)) / 2.;
            Scalar up = up_in, lo = lo_in;
            Scalar m1 = lo + g * (up - lo), m2 = lo + (1. - g) * (up - lo);
            Scalar q1 = q(m1), q2 = q(m2);
            for (int k = 0; (up - lo) >= sigma_tol_ * up && k < max_section_steps_; k++)
            {
                if (q1 > q2)
                {
                    lo = m1, q_lo = q1, m1 = m2, q1 = q2;
                    m2 = lo + (1. - g) * (up - lo), q2 = q(m2);
                }
                else
                {
                    up = m2, q_up = q2, m2 = m1, q2 = q1;
                    m1 = lo + g * (up - lo), q1 = q(m1);
                }
            }
            Scalar sigma = q1 < q2 ? m1 : m2, qs = std::min(q1, q2);
            if (up == up_in)
            {
                if ((q_up < 0. ? q(up) : q_up) < qs)
                    sigma = up;
            }
            else if (lo == lo_in)
            {
                if ((q_lo < 0. ? q(lo) : q_lo) < qs)
                    sigma = lo;
            }
            return sigma;
        }

        std::shared_ptr<Data> data_;
        std::shared_ptr<IpLineSearchBase> linesearch_;
        std::shared_ptr<AffineSearchDir> search_dir_;
        std::vector<std::pair<Scalar, Scalar>> filter_;
        std::vector<Scalar> history_;        // mu of every iteration's search direction
        bool free_mode_ = true;
        Scalar mu_max_ = -1.;
        int oracle_calls_ = 0, fixed_iterations_ = 0;
        // IPOPT's defaults
        Scalar mu_init_ = 0.1, mu_max_fact_ = 1e3, barrier_tol_factor_ = 10., mu_linear_decrease_factor_ = 0.2,
               mu_superlinear_decrease_power_ = 1.5, compl_inf_tol_ = 1e-4, sigma_max_ = 100., sigma_min_ = 1e-6,
               sigma_tol_ = 1e-2;
        int max_section_steps_ = 8;
    };

    /* fatrop's messages to the caller's writer (as fatrop's C interface does) */
    class WriterBuf : public std::streambuf
    {
    public:
        WriterBuf(void (*write)(const char *, int), void (*flush)()) : write_(write), flush_(flush) {}
        std::streamsize xsputn(const char *s, std::streamsize n) override
        {
            write_(s, (int)n);
            return n;
        }
        int overflow(int c) override
        {
            if (c != EOF)
            {
                char ch = (char)c;
                write_(&ch, 1);
            }
            return c;
        }
        int sync() override
        {
            if (flush_)
                flush_();
            return 0;
        }

    private:
        void (*write_)(const char *, int);
        void (*flush_)();
    };
    class WriterStream : public std::ostream
    {
    public:
        WriterStream(void (*write)(const char *, int), void (*flush)()) : std::ostream(&buf_), buf_(write, flush) {}

    private:
        WriterBuf buf_;
    };
} // namespace

/* what fatrop_ocp_c_create makes, with the adaptive update and its search direction */
struct RsqSolver
{
    std::shared_ptr<FatropOcpCMapping> m;
    OptionRegistry options;
    std::shared_ptr<Data> data;
    std::shared_ptr<AdaptiveMuUpdate> mu_update;
    std::shared_ptr<IpAlgorithm<OcpType>> algo;
    FatropOcpCStats stats;
    IpSolverReturnFlag flag = IpSolverReturnFlag::Unknown;
};

extern "C"
{
    RsqSolver *rsq_create(FatropOcpCInterface *ocp, void (*write)(const char *, int), void (*flush)())
    {
        RsqSolver *s = new RsqSolver();
        if (write)
            OutputStreamManager::set_stream(std::make_unique<WriterStream>(write, flush));
        s->m = std::make_shared<FatropOcpCMapping>(ocp);
        Builder builder(s->m);
        builder.with_options_registry(&s->options).build();      // every part, registered (the monotone update unused)
        s->data = builder.get_ipdata();
        auto search_dir = std::make_shared<AffineSearchDir>(s->data, builder.get_pd_solver());
        s->options.register_options(*search_dir);
        auto linesearch = builder.*get(linesearch_tag());
        s->mu_update = std::make_shared<AdaptiveMuUpdate>(s->data, linesearch, search_dir);
        s->options.register_options(*s->mu_update);
        s->algo = std::make_shared<IpAlgorithm<OcpType>>(
            search_dir, linesearch, builder.*get(initializer_tag()), s->mu_update,
            builder.*get(eq_mult_initializer_tag()), builder.*get(convergence_check_tag()),
            builder.*get(iteration_output_tag()), s->data);
        const ProblemInfo<OcpType> &info = s->algo->info();
        FatropOcpCDims &d = s->m->s;
        d.nx = info.dims.number_of_states.data();
        d.nu = info.dims.number_of_controls.data();
        d.ng = info.dims.number_of_eq_constraints.data();
        d.ng_ineq = info.dims.number_of_ineq_constraints.data();
        d.K = info.dims.K;
        d.ux_offs = info.offsets_primal_u.data();
        d.g_offs = info.offsets_g_eq_path.data();
        d.dyn_offs = info.offsets_dyn.data();
        d.dyn_eq_offs = info.offsets_g_eq_dyn.data();
        d.g_ineq_offs = info.offsets_g_eq_slack.data();
        d.max_nu = *std::max_element(info.dims.number_of_controls.begin(), info.dims.number_of_controls.end());
        d.max_nx = *std::max_element(info.dims.number_of_states.begin(), info.dims.number_of_states.end());
        d.max_ng = *std::max_element(info.dims.number_of_eq_constraints.begin(), info.dims.number_of_eq_constraints.end());
        d.max_ngineq = *std::max_element(info.dims.number_of_ineq_constraints.begin(), info.dims.number_of_ineq_constraints.end());
        d.n_ineqs = info.number_of_g_eq_slack;
        return s;
    }
    int rsq_set_option_double(RsqSolver *s, const char *name, double v)
    {
        s->options.set_option<double>(std::string(name) == "tol" ? "tolerance" : name, v);
        return 0;
    }
    int rsq_set_option_int(RsqSolver *s, const char *name, int v)
    {
        s->options.set_option<int>(name, v);
        return 0;
    }
    int rsq_set_option_bool(RsqSolver *s, const char *name, int v)
    {
        s->options.set_option<bool>(name, v);
        return 0;
    }
    int rsq_set_option_string(RsqSolver *s, const char *name, const char *v)
    {
        s->options.set_option<std::string>(name, std::string(v));
        return 0;
    }
    int rsq_solve(RsqSolver *s)
    {
        try
        {
            s->flag = s->algo->optimize();
            return s->flag == IpSolverReturnFlag::Success ? 0 : 1;
        }
        catch (std::exception &e)
        {
            PRINT_ITERATIONS << "Uncaught Exception: " << e.what() << std::endl;
            return -1;
        }
    }
    const blasfeo_dvec *rsq_get_primal(RsqSolver *s) { return &s->algo->solution_primal().vec(); }
    const blasfeo_dvec *rsq_get_dual(RsqSolver *s) { return &s->algo->solution_dual().vec(); }
    const FatropOcpCDims *rsq_get_dims(RsqSolver *s) { return &s->m->s; }
    const FatropOcpCStats *rsq_get_stats(RsqSolver *s)
    {
        IpTimingStatistics &t = s->data->timing_statistics();
        FatropOcpCStats &st = s->stats;
        st.compute_sd_time = t.compute_search_dir.elapsed();
        st.duinf_time = 0.;
        st.eval_hess_time = t.eval_hessian.elapsed();
        st.eval_jac_time = t.eval_jacobian.elapsed();
        st.eval_cv_time = t.eval_constraint_violation.elapsed();
        st.eval_grad_time = t.eval_gradient.elapsed();
        st.eval_obj_time = t.eval_objective.elapsed();
        st.initialization_time = t.initialization.elapsed();
        st.time_total = t.full_algorithm.elapsed();
        st.eval_hess_count = st.eval_jac_count = st.eval_cv_count = st.eval_grad_count = st.eval_obj_count = 0;
        st.iterations_count = s->data->iteration_number();
        st.return_flag = int(s->flag);
        return &st;
    }
    /* the last solve's iterations with mu from the oracle and in fixed mode, and the first
       n_mu iterations' mu (NaN beyond the last) */
    void rsq_barrier(RsqSolver *s, int *counts, double *mu, int n_mu)
    {
        counts[0] = s->mu_update->oracle_calls();
        counts[1] = s->mu_update->fixed_iterations();
        const std::vector<Scalar> &h = s->mu_update->history();
        for (int i = 0; i < n_mu; i++)
            mu[i] = i < (int)h.size() ? h[i] : NAN;
    }
    void rsq_destroy(RsqSolver *s) { delete s; }
}
