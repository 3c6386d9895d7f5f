"""The stage controller the loop steps: PID + disturbance observer + friction and inertia feed-forward.

Per step (dt [s], measured position x [m], reference r = (x_r, v_r, a_r))::

    v̂      = LPF_fv( (x_k − x_{k−1})/dt )                velocity estimate [m/s] (no filter if fv is None)
    u_ff   = friction feed-forward along the reference     (kind none | coulomb | model)       [N]
    u_in   = m_ff·(a_r + j_r·τ_a)                          inertia feed-forward (if inertia)   [N]
    d̂      = DOB(x_k, v̂_k, u_obs,k−1)                      (kind none | qfilter | kalman)      [N]
    u      = clamp( PID(x_r − x, v_r) + u_ff + u_in + d̂ + u_l , ±L ),   L = min(max_force_n, actuator limit)
    u_l    = learned feed-forward (``u_learn_n``, iterative learning control: stagectl.control.ilc)  [N]
    u_obs,k = u − u_ff                                      residual form, docs/friction-models.md §6.2
                                                            (u_l stays in: it is applied, like m·a_r)

Two degrees of freedom: the reference enters through the feed-forward (friction model and inertia, both
evaluated τ_a = ``feedforward.lookahead_s`` (+ effects delay) ahead, so that the force held by the zero-order
hold over the next period, after the I/O delay, matches the reference at the middle of that period), and the
feedback (PID + observer) only answers disturbances and model error. The inertia term's look-ahead uses the
reference jerk j_r = (a_k − a_{k−1})/dt (exact for the piecewise-constant-jerk moves of
:mod:`stagectl.control.trajectory`; ``feedforward.inertia_lookahead: false`` evaluates m·a_r at t_k).

Near standstill (``hold_integrator_at_rest``, with an observer): while the reference is at rest the PID
integrator is held. The observer already integrates (at low frequency d̂ integrates the PID output with gain
g = 2π·bandwidth), and at rest the plant is the friction's pre-sliding spring (Σk_i ≈ 6.4e5 N/m on the seed
stage) instead of a free mass: PID integrator × observer is then a double integrator on a spring,
L ≈ g·K_i/(k·s²) + g·K_p/(k·s), an under-damped mode at √(g·K_i/k) (≈ 2 Hz at the shipped 20 Hz gains,
≈ 5 Hz at 40 Hz gains) that made the stage drift and hunt by 50–100 nm for hundreds of ms after each stop. With
the integrator held the rest loop is first order (observer × P, no overshoot) and the observer alone removes
any steady error; the integrator resumes with the next motion.

Observer anti-wind-up against the friction feed-forward (``stuck_dob_fraction`` = δ, default 0.2, with an
observer and a friction feed-forward). While the stage is stuck its friction is indeterminate (anything up to the
static level), so the observer's estimate says nothing about the model's error there; with the stage stuck it
integrates the feedback (d̂ → d̂ + g·∫(u_pid + m·a_r) dt). After a stick-slip overshoot the stage stands *ahead* of
the reference, the feedback pulls back and d̂ winds against the feed-forward; when the reference then passes the
stuck stage the command has lost the feed-forward (d̂ ≈ −u_ff) and the stage stays stuck until the slowed feedback
has unwound it (the HIL at crossover/3: −0.8 N against 0.9 N, ``following_error``). So while the reference moves
in direction d = sgn(v_r), is ahead of the stage (d·(x_r − x) > 0), the feed-forward pushes along d and the
stage is measured stuck (its travel between the last two fresh samples <= ``STUCK_SPEED_FRACTION`` × the
reference's over the same interval; predicted positions do not count; a ratio of travels, so a gap longer than
the loop's dt cap does not make the stage look faster), the estimate may cancel at most δ of the feed-forward (the
model's own uncertainty) plus ε, the share of it the stage was seen not to need::

    d·d̂ >= −(δ + ε)·|u_ff|;   beyond it:  d̂ += d·(1 − a)·(−(δ + ε)·|u_ff| − d·d̂),   a = exp(−g·dt)
    ε = max(0, Σ λ^j·(−d·d̂)_j / Σ λ^j·|u_ff|_j)     over fresh samples while the stage *follows*

(g = 2π·f_dob/s, the observer's bandwidth at the loop's slow-down level s for a Q filter; a Kalman observer is not
slowed down, so g = 2π·f_dob), i.e. the excess goes back at the observer's own rate, moved with ``dob.shift``
(state and input history): no step in u. *Follows*: the stage's travel within ±25 % of the reference's for
``STUCK_EVIDENCE_TIME_CONSTANTS`` observer time constants in a row, |u_ff| >= ``adapt_min_force_n`` along the
motion and at least ``adapt_presliding_m`` since the motion started or reversed; there the friction is the
sliding one and the estimate is the (adapted, θ·F̂) model's error: −d·d̂ > 0 says the model is too high by that
share of u_ff. λ = exp(−dt/``STUCK_EVIDENCE_TIME_S``) per such sample. No bound before any such evidence (ε = ∞):
a model far too high keeps the stage from ever following steadily, and a bound there would lock its excess in.
Why ε: with δ alone and the model's friction more than ~25 % too high (no adaptation) the bound stopped the
observer from taking the excess back after each reversal and doubled the error (50 µm cosine, model ×1.6:
533 → 1060 nm RMS, ×2: 1072 → 2007 nm); with ε no row of that table is worse than without the bound
(``tests/control/test_stuck_dob_table.py``). In the same stuck state a PID integrator wound against the motion
(d·I < 0) goes back towards 0 at the same rate (I ← a·I). Lock-step at crossover/3 (HIL gains, exact model, a
knock that slides the stage 10 µm past its target, then 100 µm at 0.2 mm/s): 152 stuck cycles and 31.5 µm error
without the bound; 35 cycles and 14.9 µm with it (ε = 0.015 from the first move;
``tests/control/test_stuck_dob.py``). It never acts while the stage follows: the bench's scans and steps are
bit-for-bit the same figures (``stagectl bench control``). The commissioning experiments run without it.

Feed-forward through the stop (``feedforward.rest_sync_hz``, with an observer and ``kind: model``): while the
reference is at rest, a fraction λ = 1 − exp(−2π·f_s·dt) of the observer's estimate is moved into the model's
*state* each period: the model copy is fed a virtual displacement Δx = λ·d̂/(θ·Σk) (Σk: its initial, largest
pre-sliding stiffness, so the step never overshoots; |Δx| <= ``rest_sync_max_step_m``) and whatever force it
takes leaves the observer (``dob.shift``; u unchanged). The next move then starts from a model holding the force
the plant holds (d̂ ≈ 0), with its pre-sliding springs loaded as the plant's are, instead of the observer
re-learning a state mismatch during the first milliseconds of the move. The synchronisation is rate-limited
(``rest_sync_max_step_m`` per period); a move that starts before it has finished, or during a settle move from
ahead (whose reversal force u_k the model has not seen), completes it on its first sample, before the model's
first step along the reference (``rest_sync_on_start``; :meth:`StageController._sync_on_start`): otherwise the
model reverses from its old direction's level with the observer still holding the plant's force on top (+10,
−10, +60 µm moves, 30 ms dwells: 5.3 µm ahead on the third).
The model copy is fed at x_r; with the stage stuck more than ``rest_spring_range_m`` off it, d̂ also holds that
offset's force. Loaded into the model at x_r, the next move's first |x_r − x| of reference travel (which the stuck
stage does not make) re-loaded the model's springs and pushed the stage ahead. So with the stage stuck further
*ahead* (in the model's direction of travel) the model is fed at the stage's position x instead: the reference's
travel up to the stage leaves its state alone, as the plant's; with the stage further *behind* (or sliding) there
is no synchronisation, and a model fed at the stage earlier is fed at x_r again (fresh plant 111, stuck 1.2 µm
ahead: cosine 4.40 -> 0.14 µm RMS; docs/control.md §2.10).
Creep gate (SYNC_CREEP_M, without ``learn_moves_fraction``): the observer's estimate *against* the model's
direction of travel d is an unloaded pre-sliding state only where force was taken off a stage that holds;
while the stage slides on in d after the reference stopped (new furthest points in d, SYNC_CREEP_M apart) its
elements are saturated in d and the estimate is the lower sliding level it has. So once it has slid on, the
sync (and the start-edge load of a move that goes on in d) unloads the model by at most what the estimate
(low-passed, without the sync's own loads) has dropped since the stage last slid on plus θ·Σk times its travel
back from its furthest point; a move that reverses loads all of it. Unloaded anyway, the model re-loaded over
the next move's first nanometres and pushed the stage ahead (generated plant 36 commissioned, a sticky 8 Hz
design: 72 nm ahead at the cosine's start, 11.0 against 3.5 nm RMS without the rest additions, which
commissioning then dropped with the 4/4 steps they settle; tests/commission/test_rest_sync_creep.py). Not with
the learning from moves, which takes that level into θ from a move started with the estimate loaded.

Rest spring (``rest_stiffness_fraction`` = φ, with an observer and ``kind: model``; held released while ILC takes
part, since its load at each stop would differ between repetitions): at standstill the stage is
stuck on the friction's pre-sliding spring (Σk ≈ 6.4e5 N/m on the seed stage). With a free-mass nominal plant
the observer estimates that spring's force k·(x − x_r) as a disturbance and cancels it, so only P (+D) removes a
position error: the rest mode is g·K_p/(k + K_p) ≈ 9 s⁻¹ (100-500 ms settles). With the rest spring the
observer's nominal plant at rest is the mass on k_v = φ·min(θ, 1)·Σk about the reference::

    d̂_rest = d̂ − s,    s_k = α·s_{k−1} + (1 − α)·k_v·clamp(x_k − x_r, ±rest_spring_range_m)   [N]

(α as in the Q filter), so it estimates only F(x_r) − u_ff + (k − k_v)·(x − x_r) and the stage's own spring
pulls it to x_r: the quasi-static rest mode becomes g·(K_p + φ·k)/(k + K_p) ≈ g·φ. When the reference starts
to move, s is folded into the observer (d̂ and its input history move by −s: u continuous). Linear margins of
the rest loop (PD + observer + spring, 1 kHz, one cycle of I/O delay, φ = 0.5; ``stagectl tune`` prints them):
on the stuck plant (2 kg on 6.4e5 N/m with the model's Σσ1 = 226 N·s/m) PM 30.8°, GM 6.1 dB (φ = 0: 39.9°,
6.6 dB); on a *free* mass the spring (a ~3e5 N/m position gain) makes the rest loop unstable, its force bounded
by k_v·rest_spring_range_m (64 mN at 200 nm): it relies on the stage being stuck at rest. Without a guard a
plant with friction ×0.2 and stiffness ×0.1 of the model hunted by 0.5–1 µm in the holds.

Why min(θ, 1): the spring is a position gain of the rest loop, and the loop's margins fall as k_v grows (stuck
plant above, φ = 0.5: θ = 0.5 → PM 36.5°, GM 6.5 dB; 1 → 30.8°, 6.1 dB; 1.5 → 21.9°, 5.5 dB). θ is learned from
the force *level* while sliding (the adaptation, the learning from moves; 1 ± ``adapt_max_change_fraction``) and
says little about the stiffness the stage is stuck on at rest, so a θ above 1 must not raise the loop gain beyond
the one designed at θ = 1; following θ down keeps the spring below a plant whose friction the model
overestimates (less gain: more margin). The cost is that a plant stiffer than its model keeps more of its own
spring in the observer (a slower rest mode), never a thinner margin. ``stagectl tune`` reports the rest loop over
the θ range the configuration allows, worst case (with the cap: θ = 1).

Guard (the spring acts only while the stage behaves stuck): it is *released* — s folded into the observer as
at a move start, bumpless — when |x − x_r| > ``rest_spring_release_m`` (5 µm: the stage has slid) or when
x − x_r swings from beyond ±``rest_spring_rearm_m`` (50 nm) to beyond the other side and back (hunting: a
stuck stage pulled in by the spring approaches without such a swing). After ``rest_spring_max_release_count``
releases in one standstill (default 1) it stays off until the reference moves; with more, it is re-armed once
|x − x_r| stayed within ``rest_spring_rearm_m`` for ``rest_spring_rearm_s``, bumplessly: s starts at
k_v·(x − x_r) and the observer is moved by +s, so the command does not step (the spring's force then builds in
over the observer's time constant, a few samples). Every move re-arms it. On plants with 0.01–0.5 of the
model's stiffness and 0.01–1 of its friction the guarded steps hold with no limit cycle and a late error of
±2–3 nm, as without the spring; they settle at most ~0.1 s later than without it (one burst of hunting before
the release), often faster. The seed-stage steps are unchanged (the guard does not trigger there).

Stiffness test (``rest_spring_held_fraction`` = ρ, 0.5): the guard above acts only once the stage has hunted or slid,
but the linear rest loop is unstable as soon as the stage is held by less stiffness than the spring assumes (tune's
*stiffness margin*: the rest loop meets PM 40° / GM 8 dB down to 0.47 of the model's stiffness for config/sim.yaml).
A witness observer (a Q filter on the whole command, never shifted) gives the force the stage takes,
F = LPF(u − m·a), and the position at the sample F is centred on goes through the same low-pass (x_f). After each
reversal of x_f (REST_HELD_MIN_TRAVEL_M hysteresis; a pre-sliding contact is at its stiffest there) the secant
k̂ = Σ(Δx·ΔF)/Σ(Δx²) over the first REST_HELD_JUDGE_TRAVEL·REST_HELD_MIN_TRAVEL_M (10 nm) is judged once, within
``rest_spring_range_m`` of x_r only (beyond it the spring's force is clamped: no stiffness); k̂ < ρ·min(θ, 1)·Σk
releases the spring as the guard does (``rest_spring_release_reason`` "not held"). Each standstill's test starts
afresh (a move resets it); with no move since the start the contact's history is unknown and the branch from the
arming point is judged too (after REST_HELD_WARMUP_TIME_CONSTANTS of the witness: its start-up transient is no
stiffness).

Held before the full spring (``rest_spring_unconfirmed_kp_fraction`` = κ_u, default 0): the test above judges only
after a reversal, and until then the full spring acted on whatever the stage was: on a free 2 kg mass started
1 / 20 / 100 nm off, 54 / 369 / 2115 nm at most against 11 / 151 / 757 nm without the spring. So at each standstill
the spring is k_v only once the stage is *seen held*: it takes a force |F| >= REST_HELD_FORCE_FRACTION·θ·F_c (the
witness F = LPF(u − m·a) above, after its start-up; F_c the model's Coulomb level; a free mass without a load takes
no force, F ≈ 0; one under a constant load takes it, and is seen held), or a branch was judged k̂ >= ρ·min(θ, 1)·Σk. Before that it is min(k_v, κ_u·K_p), and the rest loop on a free mass is the linear
loop with that spring (``stagectl tune``'s rest/free line: with κ_u = 0 the spring-less rest loop, config/sim.yaml
PM 57.1°, GM 10.5 dB). A move's stop leaves the stage holding the friction force it slid on, so after a move the
seed stage is seen held at once and the bench's figures are bit for bit those of the spring without this gate (a
settle move from ahead can leave the stage holding only ~0.1·F_c: hence the low fraction);
the free mass above: 11 / 151 / 757 nm, as without the spring. Not by design for a *soft* stage (held by friction
but on less stiffness than the model's): it takes the force, gets the full spring and relies on the test above as
before (docs/control.md §2.2).

Rest integral (``rest_integral_hz`` = f_r, off by default; with ``kind: model``, without the rest spring;
docs/control.md §2.10): at standstill, once the stage no longer approaches the target (its speed
towards it, low-passed over REST_INTEGRAL_VELOCITY_S, at most REST_INTEGRAL_STILL_M_S for REST_INTEGRAL_DWELL_S;
once the integral has acted on the stiff side, the approach it causes does not pause it)
and while |e| > REST_INTEGRAL_DEADBAND·``settle.tolerance_m``, the observer's estimate is moved each period by::

    δ = 2π·f_r·min(θ, 1)·k_t·clamp(e, ±rest_spring_range_m)·dt,   |Σδ| <= θ·F_c over the standstill   [N]

(e = x_r − x; k_t the model's tangent stiffness towards the target: Σk ahead of it, ~0 behind; ``dob.shift``, so
the observer does not integrate it again): a stage stuck off the target converges at ≈ 2π·f_r instead of
g·K_p/Σk. Behind the target (k_t < REST_INTEGRAL_SOFT_FRACTION·Σk: the elements slip, the stage is held at its
break-away level and the observer takes the P force as a disturbance) it pushes at the break-away gain instead,
k_b = min(Σk, max(F_s − F_c, REST_INTEGRAL_GAP_MIN·F_c)/rest_spring_range_m), while the stage creeps in at no more
than REST_INTEGRAL_SOFT_STILL_M_S (both speeds low-passed over REST_INTEGRAL_VELOCITY_S), holds it while the stage
approaches at up to REST_INTEGRAL_STILL_M_S, and takes it back (``dob.shift``) once the approach is faster (the
break-away): the stage slides only as far as the force went past its break-away level, sticks again and is pushed
anew (stick-slip positioning in small increments). It stops for the standstill when |e| > ``rest_spring_release_m``
or e swings across ±``rest_spring_rearm_m`` twice, and each standstill starts afresh; what it added stays in the observer, which
``feedforward.rest_sync_hz`` hands to the model before the next move. Without an observer δ goes into the PID's
integrator instead (nothing else moves the stuck stage: the integrator alone gives K_i/Σk, ≈ 0.02 s⁻¹ on generated
plant 29), the bound is REST_INTEGRAL_BOUND_X_NO_OBSERVER·θ·F_c, and ``feedforward.rest_sync_hz`` hands the force
it added (only that, not what the integrator carried from the move) to the model (:meth:`_rest_sync_integral`);
a move that starts before that finished loads the rest of it on its first sample (``rest_sync_on_start``;
:meth:`_sync_on_start_integral`: otherwise the integrator carried it into the move, fresh plant k105's matched twin
a following-error fault).

Rest loop gains (``rest_kd_fraction`` = κ_d, ``rest_dob_bandwidth_fraction`` = κ_g, ``rest_spring_section_count`` = n,
with a Q-filter observer). Stuck, the stage is a lightly damped spring-mass (2 kg on Σk ≈ 6.4e5 N/m: 90 Hz, ζ ≈ 0.1)
and above that resonance it has *more* gain than the free mass (1/(m·ω² − k)); the observer's high-frequency
velocity feedback (≈ m·g) and K_d act on it with the loop delay, so the moving loop's gains alone give the stuck
stage PM 40.0°, GM 6.6 dB, and the spring (one section at the observer's bandwidth) 30.8°, 6.1 dB. While the stage is
held — the reference at rest, no settle move, and |v̂| <= ``REST_GAINS_ENTER_M_S`` for ``REST_GAINS_DWELL_S`` — the
loop runs K_d·κ_d and the observer at κ_g·bandwidth (bumpless retunes, as :meth:`set_timing_scale`, with which they
compose; K_d's change goes into the derivative filter's state, ė_f·K_d continuous, not into the integrator:
:meth:`_set_rest_gains`), and the spring's force goes through n sections of the observer's own low-pass (at its configured
bandwidth, not κ_g·bandwidth: the spring's timing stays that of the moving design), s = LPF_g^n(k_v·clamp(x − x_r)). The
moving gains return as soon as |v̂| > ``REST_GAINS_EXIT_M_S`` (the stage slips: on a free mass the rest gains have
less damping; without this gate a 0.9 µm soft-side stop without the settle move took 0.9 s instead of 63 ms) or the
reference moves. ``config/sim.yaml``: κ_d 0.3, κ_g 0.75, n 2: stuck stage PM 53.7°, GM 8.4 dB over θ 0.5..1
(``stagectl tune``; docs/control.md §2.9).

Feed-forward adaptation (``feedforward.adapt_bandwidth_hz`` = f_a, γ = 2π·f_a, with an observer, while the
reference moves and no learned force is applied)::

    u_ff = θ·F̂(β·x_r)                    F̂: the model fed β times the reference increments
    within adapt_presliding_m of the last reversal:  dβ/dt = γ·β·d̂/(θ·(F̂ − F̂_rev))   (stiffness ×β, Vs ÷β)
    beyond it (sliding):                              dθ/dt = γ·d̂/F̂                  (force level ×θ)

No adaptation in the first ``adapt_presliding_m`` of a move that starts with the rest spring loaded: the
observer then carries the folded spring force for a while, which is not an error of the model (learning from it
made the cosine after a positioning move 20x worse: 41.6 against 7.0 nm RMS in the commissioning's check).

No stiffness evidence (β stays) from a reversal at which
the stage was off the reference by more than ADAPT_LAG_FRACTION of the reversal's force through the friction's
spring, θ·Σk·|e_rev| > ADAPT_LAG_FRACTION·max(|F̂_rev|, F_c): the plant's branch then starts at the stage's turning
point, not the model's, and the stage rings on that spring (a junction of two 200 µm approach moves: 0.39 µm
short, 0.25 N; the observer's +26 mN against the model's first 0.06 N of branch force moved β +0.3 % in one
step, +0.4 % per junction on an exact model).

θ, β ∈ 1 ± ``adapt_max_change_fraction``; frozen at rest and while |F̂| (|F̂ − F̂_rev| for β) is below
``adapt_min_force_n`` (half of it for β). A change of θ moves (θ_old − θ_new)·F̂ into the observer (``dob.shift``): u
is continuous. The observer's estimate in the residual form is exactly the model's error, so the model takes
over what the observer would otherwise re-learn at every reversal; it is a model correction, not a learned
signal, so it carries over to any motion. One learner at a time: while ILC takes part in the motion (it is
armed and records — its first repetition applies no force — or applies a learned force; ``learn_active`` or
u_learn ≠ 0 in :meth:`StageController.step`), θ and β stay put, for this adaptation and for the learning from
moves below alike, so ILC learns against a fixed feed-forward.

Learning from earlier moves (``feedforward.learn_moves_fraction`` = κ, with an observer and ``kind: model``): the
continuous adaptation above is slow (1 Hz: a 30 ms move moves θ by ~1 %), and it cannot be faster without
hurting the scans (the 10 µm cosine's error grows 5x at 5 Hz). Every move instead contributes a least-squares
fit of the model's error *at the reference* to its two parameters, applied when the reference comes to rest::

    y  = d̂ − d̂_0 + (θ − θ_0)·F̂ + Q·(θ·k_t·e)          model error at the reference [N] (e = x_r − x)
    g  = Q·( F̂ − F̂_0 ,  θ·(x_r − x_b)·k_t )             ∂u_ff/∂θ, ∂u_ff/∂ln β since the move's start [N]
    C ← λ·C + Σ g·gᵀ,  r ← λ·r + Σ g·(y + gᵀ·p_0)       over the moves (λ = LEARN_FORGET = 0.9)
    p* = (C + ρ·diag C)⁻¹ (r + ρ·diag C·(1, 0)),  p = (θ, ln β) ← p + κ·(p* − p)   (ρ = LEARN_RIDGE = 0.05)

Q is the observer's low-pass with its delay (its estimate lags the model error the same way), k_t the model's
stiffness for going on in the direction of motion (:meth:`FrictionFeedforward.tangent_n_m`; GMS: Σk_i of the
elements not yet slipping; ~0 when sliding, so β is learned in pre-sliding only), x_b the start of the branch
(the last reversal, or the start of the move). The term θ·k_t·e matters: a stage lagging the reference by e sits
lower on its friction curve, F(x) = F(x_r) − k·e, and the observer estimates that spring too; without it the
fit took a stiffness error for a scale error (on a model with only its stiffness 20 % low it learned θ 1.05,
β 1.02 in four steps; with it θ 1.01, β 1.21, true β 1.25). The ridge keeps θ and β apart where they are nearly collinear (pre-sliding)
and, with the forgetting, keeps one noisy move from walking the model away (with the exact model θ, β stay
within 1 ± 0.03 over 20 moves). Learned only where identifiable (confidence gates): not from a move that starts
while the observer still carries more than LEARN_START_FRACTION of the move's regressor RMS (at rest the friction
is indeterminate; what the stop synchronisation has not yet moved into the model is a mismatch of its state, which
sliding erases: after a fast 200 µm move and 0.1 s at rest it was 0.56 N, and learned as θ 0.66 with the exact
model), nor from a move shorter than LEARN_MIN_TIME_CONSTANTS observer time constants (there the estimate is
mostly the observer's transient: alternating 0.3 µm moves at the default move limits walked the exact model to
θ 1.33), nor from one shorter than LEARN_MIN_MOVE_S whatever the observer (short moves bias β low: with a 150 Hz
observer, 15 time constants admitted 5-7 µm moves, which walked the exact model to β 0.88). The baseline is the
model force at rest, the step before the move (a static model jumps in the move's first step). θ changes
bumplessly (its force leaves the observer), β changes only the next
increments. Measured on the seed stage's 10 µm steps with the 20 %-wrong model (``stagectl bench control``):
the first move from a relaxed start cannot profit (nothing learned yet; it settles in ~60 ms as before), the
later ones in 25–31 ms instead of 51–64 ms. Not while ILC takes part in the motion (above); a retune that
replaces the model forgets what was learned.

Evidence gates for both learners (docs/control.md §2.3; on a plant equal to the model they moved θ to 0.927
from two pairs of 200 µm approach moves, and to 1.03 / β 0.97 from a 10 mm/s move):

* transients: a sample is evidence only ADAPT_SETTLED_TIME_CONSTANTS observer time constants after the
  reference's inertia force last moved by more than ADAPT_LAG_FRACTION of max(|F̂|, F_c) within one time constant,
  m·|a_r − LPF_g(a_r)| <= ADAPT_LAG_FRACTION·max(|F̂|, F_c), and after such a transient also the stage's lag
  θ·Σk·|e − LPF_g(e)| by as little (the lag alone does not shut it: a wrong model's lag is its evidence). The
  adaptation waits for it; the learning from moves sums only such samples and counts its time constants over them.
  A sample interval longer than IRREGULAR_DT_PERIODS·T (a skipped slot, a stale sample) restarts the count too:
  the observer takes the force the actuator applied in the slots it did not see for a disturbance, and that is no
  model error (``stagectl bench timing --stages plant_io``, 10 µm cosine, disturbed/clean RMS, seeds 1-6:
  1.48 2.18 1.46 1.59 1.56 1.68 before, see docs/control.md §4).
* the rest state: a move is not evidence when its fit with the start's estimate d̂_0 as baseline and with 0 differ
  by more than LEARN_BASELINE_TOL in θ or ln β (Δp = d̂_0·A⁻¹·Σg): at rest d̂_0 may be a force that stays or a
  mismatch of the model's pre-sliding state that sliding erases, and the move cannot tell which.
* significance: θ and β are each moved only where the accumulated fit differs from them by more than
  LEARN_SIGNIFICANCE standard errors (residuals of the move's fit, one independent sample per two observer time
  constants), by at most LEARN_MAX_STEP per move.

Settle move (``settle.move_s``, off by default; :mod:`stagectl.control.settle_move`): a move that ends with
the stage behind the reference in its direction by more than ``settle.move_min_m`` is continued once, from the
first sample at rest, by a quintic c from the stage's error e₀ and speed to rest at the target in
T = max(move_s, √(10/√3·m·|e₀|/F)) (F = ``settle.move_force_n``, the quintic's peak inertial force; without it
T = move_s; :meth:`StageController.settle_move_duration`): the PID's
reference is x_r − c, the inertia term m·(a_r − c̈); the friction model is held, the reference is unchanged (so
the settle detector, the learning from moves and the adaptation see the move as it was commanded), and the rest
logic (rest spring, rest synchronisation, integrator hold) waits until τ = T. Not while ILC takes part. Measured
in docs/control.md §2.5–2.6 (20 %-wrong steps 63, 25, 28, 31 → 14, 25, 22, 22 ms with move_s 5 ms, F 0.145 N,
move_min_m 0.1 µm; a fixed T = 14 ms gave 32, 24, 30, 31 ms and slowed some later moves).

Settle move from ahead (``settle.ahead_stiffness_fraction`` = γ > 0, with ``move_s`` > 0): a move that ends with
the stage *ahead* in the direction it moved (and started in) by more than ``move_min_m``, stuck on the stiff
pre-sliding branch, gets the same continuation and the friction spring's force along its planned travel,

    u_k(τ) = γ·θ·β·Σk·(e₀ − c(τ + τ_a))   [N]   (θ, β after the stop's learning; τ_a the feed-forward look-ahead)

while the planned travel δ = e₀ − c stays in the linear part of the model's reversal, |δ| <= min 2·W_i/(β·k_i);
beyond it the elements slip and the force follows Masing's curve γ·θ·Σ min(β·k_i·|δ|, 2·W_i)·sgn(δ)
(:func:`~stagectl.control.settle_move.reversal_force`; GMS W_i = α_i·max(F_s, F_c), Maxwell slip its W_i, other
models one element Σk, max(F_s, F_c)), never more than the friction's whole swing; and the friction the
feed-forward then implies, θ·f_ff + u_k (f_ff the model's friction held at the stop), stays within the model's
range ±θ·ΣW_i. Without these bounds a stage 4.4 µm ahead (a ``stop`` mid-move after short dwells) was pulled with
k·e₀ = 2.8 N against at most ~1.25 N of friction reversal: it overshot by 11 µm, the second continuation added
its own unbounded pull on top of the first's, and the stage swung ±70 µm into a following-error fault. The force is
added to the command and kept out of the observer's input (u_obs = u − u_ff − u_k); at τ = T it is handed to the
observer (d̂ += u_k, ``dob.shift``: no step in u; a retune during it does the same at once, and the rest of the
continuation runs without the spring force). If at its end the stage is still off by more than move_min_m/2, one
second continuation follows from there, keeping the first's force and adding its own with the gain × the first's
planned / measured travel e₀/(e₀ − e₁), bounded by ``AHEAD_RATIO_MAX`` (the elements' stiffnesses scaled alike;
the sum of both forces within the friction range above). Feed-forward planned at each start: the loop
and its margins are unchanged. docs/control.md §2.8: a too-high model's first step 24–64 → 15–24 ms.

Settle detector (``settle``): :class:`~stagectl.control.settle.SettleDetector` reports in-position (reference
at rest, |e| <= ``settle.tolerance_m`` for ``settle.dwell_s``) as the ``in_position`` term (1.0 / 0.0).

Terms in ``Command.terms`` (newtons): ``u_pid`` (= ``u_p`` + ``u_i`` + ``u_d``), ``u_dob``, ``u_ff``,
``u_inertia``. ``Command.limited`` holds ``"force"`` when the output was clamped and ``"anti_windup"``
when the integrator was held.

Masses: ``mass_kg`` is the nominal moving mass; ``dob.nominal_mass_kg`` and ``feedforward.mass_kg`` override
it for the observer and the inertia feed-forward. If ``mass_kg`` is not set, the stage model's ``mass_kg``
is used.

Model: the controller never reads a file. ``feedforward.model_file`` is loaded by the configuration layer
(:func:`stagectl.config.load_app_config`), which stores the resolved :class:`~stagectl.friction.StageModel`
in ``feedforward.model`` (see :func:`resolve_model`); a caller may also hand a model to
:class:`StageController` directly.

Real-time safety: ``step`` is (floats only, no allocation beyond the Command). ``StageController(...)``,
``retune`` and ``prepare_retune`` are not (the Kalman form designs its gain with python-control); for a
reload from another thread use ``request_retune`` (prepares there, swaps at the next cycle boundary).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stagectl.clock import Timing
from stagectl.control.api import Command, Reference
from stagectl.control.dob import DobConfig, KalmanDob, QFilterDob, make_dob
from stagectl.control.friction_ff import CoulombFeedforward, FrictionFeedforward
from stagectl.control.pid import Pid, PidConfig, check_dt
from stagectl.control.settle import SettleConfig, SettleDetector
from stagectl.control.settle_move import SettleMove, reversal_force
from stagectl.errors import ConfigError
from stagectl.friction import StageModel, parse_friction
from stagectl.friction.base import FrictionModel
from stagectl.friction.effects import Effects
from stagectl.schema import load, param

#: names of the terms in ``Command.terms`` (telemetry columns), in newtons except ``in_position`` (1.0 in
#: position, 0.0 not; the settle detector's flag, not a force)
TERM_NAMES = ("u_pid", "u_p", "u_i", "u_d", "u_dob", "u_ff", "u_inertia", "in_position")
#: the force terms of TERM_NAMES (newtons)
FORCE_TERM_NAMES = TERM_NAMES[:-1]


@dataclass(frozen=True)
class FeedforwardConfig:
    """Feed-forward settings (YAML ``controller.feedforward``)."""

    kind: str = param("model", desc="friction feed-forward: none, coulomb (static baseline) or model (GMS...)",
                      choices=("none", "coulomb", "model"))
    model_file: Path | None = param(None, desc="stage model file (friction + effects) for kind: model")
    friction: FrictionModel | None = param(None, desc="inline friction model (model: tag + parameters)",
                                           parse=parse_friction)
    effects: Effects | None = param(None, desc="inline effects (overrides the model file's)")
    inertia: bool = param(True, desc="add the inertia feed-forward m·a_ref")
    inertia_lookahead: bool = param(True, desc="evaluate the inertia feed-forward m·a_ref at the look-ahead "
                                    "(a_ref + jerk·τ_a, jerk from the reference's change of a_ref)")
    mass_kg: float | None = param(None, unit="kg", desc="mass of the inertia feed-forward (None: controller mass_kg)",
                                  gt=0.0)
    coulomb_n: float = param(0.0, unit="N", desc="kind coulomb: Coulomb level F_c", ge=0.0)
    viscous_n_s_m: float = param(0.0, unit="N*s/m", desc="kind coulomb: viscous coefficient", ge=0.0)
    reversal_threshold_m: float = param(5e-9, unit="m", desc="move-back that confirms a reversal", ge=0.0)
    reversal_velocity_m_s: float = param(1e-5, unit="m/s", desc="reverse velocity that confirms a reversal",
                                         gt=0.0)
    rest_sync_hz: float = param(
        0.0, unit="Hz", desc="with an observer and kind: model: at standstill, rate at which the observer's "
        "estimate is moved into the friction model's pre-sliding state (the model is loaded by a virtual "
        "displacement until its force is the one the plant holds; 0: off)", ge=0.0, le=200.0)
    rest_sync_max_step_m: float = param(
        2e-9, unit="m", desc="largest virtual displacement fed to the model per period by rest_sync_hz", gt=0.0)
    rest_sync_on_start: bool = param(
        True, desc="with an observer and kind: model: a move that starts before the standstill's rest_sync_hz "
        "synchronisation has finished (a short dwell), or during a settle move from ahead, first loads the rest of "
        "the observer's estimate (and the settle move's reversal force) into the model's pre-sliding state, "
        "before the model's first step of the move (false: the observer carries it into the move); without an "
        "observer, with rest_integral_hz, the rest of the rest integral's force, from the PID integrator")
    adapt_bandwidth_hz: float = param(
        0.0, unit="Hz", desc="with an observer: rate γ/2π at which the friction feed-forward's force scale θ "
        "and input scale β take over the observer's estimate while the reference moves (u_ff = θ·F̂(β·x_r), "
        "dθ/dt = γ·d̂/F̂; 0: off)",
        ge=0.0, le=50.0)
    learn_moves_fraction: float = param(
        0.0, desc="with an observer and kind: model: at the end of every move (the reference comes to rest) θ "
        "and β are moved this fraction of the way to the least-squares fit of the observer's estimate during "
        "the move (the model's sensitivities to θ and β, filtered like the observer, as regressors); learns "
        "the model's scale and stiffness from earlier moves (0: off)", ge=0.0, le=1.0)
    adapt_min_force_n: float = param(
        0.1, unit="N", desc="θ adapts only while |F̂| (model force) is at least this (no division near a zero "
        "crossing)", gt=0.0)
    adapt_presliding_m: float = param(
        5e-6, unit="m", desc="adaptation: within this travel after a reversal (or the start of a motion) the "
        "observer's estimate is taken as an error of the model's stiffness and adapts β, the scale of the "
        "model's input (stiffness ×β, Stribeck velocity ÷β); beyond it, θ (0: θ only)", ge=0.0)
    adapt_max_change_fraction: float = param(
        0.5, desc="θ and β stay within 1 ± this (the model is trusted to this fraction)", gt=0.0, lt=1.0)
    lookahead_s: float | None = param(
        None, unit="s", desc="evaluate the reference this far ahead, plus effects.delay (None: period_s/2, the "
        "zero-order-hold mid-point; add the I/O delay of the actuator path)", ge=0.0, le=0.1)
    model: StageModel | None = param(
        None, desc="the resolved stage model (inline friction or model_file, with effects); set by the "
        "configuration loader, not a YAML key", parse=lambda value, path, problems: _not_a_key(path, problems))


#: FeedforwardConfig keys read live at each step: a retune that changes only these keeps the feed-forward object
#: (its friction state, θ and β); any other key defines the friction feed-forward and rebuilds it
FF_LIVE_KEYS = frozenset({"inertia", "inertia_lookahead", "mass_kg", "rest_sync_hz", "rest_sync_max_step_m",
                          "rest_sync_on_start",
                          "adapt_bandwidth_hz", "adapt_min_force_n", "adapt_presliding_m",
                          "adapt_max_change_fraction", "learn_moves_fraction"})


def same_friction_ff(a: FeedforwardConfig, b: FeedforwardConfig) -> bool:
    """Whether ``a`` and ``b`` define the same feed-forward object: equal in every key but :data:`FF_LIVE_KEYS`,
    models by value (their ``spec()``: two loads of one model file are the same model; ``model_file``, the
    file's name, is left out for the model the loader resolved from it)."""
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name in FF_LIVE_KEYS or x is y or (f.name == "model_file" and a.model is not None):
            continue
        if type(x) is type(y) and hasattr(x, "spec"):
            x, y = x.spec(), y.spec()
        if x != y:
            return False
    return True


def _not_a_key(path: str, problems: list[str]) -> None:
    """Parse hook of :attr:`FeedforwardConfig.model`: the loader fills it, a YAML file may not."""
    problems.append(f"{path}: unknown key (the model is given with friction: or model_file:)")


@dataclass(frozen=True)
class ControllerConfig:
    """Controller settings (YAML ``controller:``)."""

    mass_kg: float | None = param(None, unit="kg", desc="nominal moving mass (None: the model file's mass_kg)",
                                  gt=0.0)
    max_force_n: float = param(10.0, unit="N", desc="output force clamp", gt=0.0)
    velocity_cutoff_hz: float | None = param(None, unit="Hz", desc="low-pass of the velocity estimate (None: raw)",
                                             gt=0.0)
    pid: PidConfig = param(default_factory=PidConfig, desc="PID gains")
    dob: DobConfig = param(default_factory=DobConfig, desc="disturbance observer")
    feedforward: FeedforwardConfig = param(default_factory=FeedforwardConfig, desc="feed-forward")
    hold_integrator_at_rest: bool = param(
        True, desc="with an observer: hold the PID integrator while the reference is at rest (the observer "
        "integrates already; both together hunt on the friction's pre-sliding stiffness)")
    settle: SettleConfig = param(default_factory=SettleConfig, desc="in-position (settle) detector")
    rest_stiffness_fraction: float = param(
        0.0, desc="with an observer and kind: model: at standstill the observer's nominal plant is the mass on a "
        "spring of this fraction of the model's pre-sliding stiffness about the reference, so that the stuck "
        "stage's own friction spring is not estimated away as a disturbance (0: off)", ge=0.0, le=1.0)
    rest_spring_range_m: float = param(
        2e-7, unit="m", desc="the rest spring's displacement |x - x_ref| is clamped to this (the pre-sliding "
        "range it stands for); beyond it feedforward.rest_sync_hz loads the model at the stage's position (stage ahead "
        "of x_ref) or not at all (behind)", gt=0.0)
    rest_spring_release_m: float = param(
        5e-6, unit="m", desc="the rest spring is released (folded into the observer, bumpless) when |x - x_ref| "
        "exceeds this at standstill: the stage has slid, not stuck (25x the default rest_spring_range_m)", gt=0.0)
    rest_spring_rearm_m: float = param(
        5e-8, unit="m", desc="hunting band of the rest spring: it is released when x - x_ref swings from beyond "
        "+this to beyond -this and back (an oscillation, not a stuck stage); once released it is re-armed only "
        "after |x - x_ref| stayed within this for rest_spring_rearm_s", gt=0.0)
    rest_spring_rearm_s: float = param(
        0.05, unit="s", desc="dwell within rest_spring_rearm_m before the released rest spring is re-armed", ge=0.0)
    rest_kd_fraction: float = param(
        1.0, desc="with a Q-filter observer: the PID's derivative gain while the reference is at rest, as a fraction "
        "of pid.kd_n_s_m (the rest loop's gain at the stuck stage's pre-sliding resonance; 1: unchanged)",
        gt=0.0, le=1.0)
    rest_dob_bandwidth_fraction: float = param(
        1.0, desc="with a Q-filter observer: the observer's bandwidth while the reference is at rest, as a fraction "
        "of dob.bandwidth_hz (switched bumplessly; 1: unchanged)", gt=0.0, le=1.0)
    rest_spring_section_count: int = param(
        1, unit="count", desc="first-order low-pass sections at dob.bandwidth_hz that the rest spring's force goes "
        "through (1: as the observer's own filter; 2: less of the spring at the stuck stage's resonance)", ge=1, le=2)
    rest_integral_hz: float = param(
        0.0, unit="Hz", desc="with kind: model: at standstill, once the stage is still, an "
        "integral action on the tracking error of gain 2*pi*this*min(theta, 1)*k_t (k_t: the model's stiffness for "
        "moving on towards the reference, sum(k) on the stiff side, ~0 where its elements slip; the error clamped to "
        "rest_spring_range_m, the force it adds bounded by the model's Coulomb level, twice that without an "
        "observer) added to the observer's estimate (without an observer: to the PID's integrator): a stage stuck "
        "off the target converges at about 2*pi*this per second instead of the moving "
        "loop's g*K_p/sum(k); stopped for the standstill when the stage slides or hunts (rest_spring_release_m, "
        "rest_spring_rearm_m). Meant with feedforward.rest_sync_hz, which hands the force it finds to the model "
        "before the next move (0: off)", ge=0.0, le=50.0)
    rest_spring_max_release_count: int = param(
        1, unit="count", desc="releases of the rest spring in one standstill after which it stays off until the "
        "reference moves again (1: no re-arm before the next move; a re-arm on a stage that is not stuck costs "
        "one more release)", ge=1, le=100)
    rest_spring_held_fraction: float = param(
        0.5, desc="the rest spring is released (bumplessly) as soon as the stage's stiffness measured at standstill "
        "is below this fraction of the model's pre-sliding stiffness times min(theta, 1): after each reversal of the "
        "stage's position (both it and the force it takes, u - m*a, through the observer's low-pass; a reversal is a "
        "5 nm turn back) within rest_spring_range_m of the reference, the secant slope of force over position along "
        "the first 10 nm of the new branch, judged once per branch; the stage is then not held and the spring would "
        "be a negative stiffness of the loop; stagectl tune prints the lowest fraction at which the rest loop meets "
        "its margins (0: no stiffness test)",
        ge=0.0, le=1.0)
    rest_spring_unconfirmed_kp_fraction: float = param(
        0.0, desc="with rest_spring_held_fraction > 0: the rest spring's stiffness, as a fraction of the PID's K_p "
        "(at most the full spring), at a standstill until the stage is seen held: it takes a force of at least 5 % "
        "of the model's Coulomb level (a free mass takes none) or the stiffness test judges a branch held; "
        "then the full spring builds in through its low-pass (no step in the command). The rest loop on a free mass "
        "runs with this spring (stagectl tune's rest/free line; 0: as without a spring)", ge=0.0)
    design_delay_samples: int | None = param(
        None, unit="samples", desc="loop delay in whole periods for the margin analysis and the design check of "
        "stagectl tune / bench (None: io.delay_cycles for plant_io, else 1; 2 with a sensor not sampled on SYNC)",
        ge=0, le=8)
    stuck_dob_fraction: float = param(
        0.2, desc="observer anti-wind-up: while the reference moves ahead of a stage measured stuck (its travel "
        "between fresh samples is at most a quarter of the reference's), the observer's estimate may cancel at "
        "most this fraction of the friction feed-forward (the model's own uncertainty) plus the share it was "
        "seen to take back while the stage last followed the reference (a model too high); no bound before "
        "such evidence; a larger estimate is returned to that bound at the observer's rate (inf: off)",
        ge=0.0, allow_inf=True)
    stale_predict_cycles: int = param(
        2, unit="cycles", desc="stale samples in a row (late or dropped) stepped on a predicted position (the last "
        "measured tracking error held), so feedback and observer keep their sample rate; later ones hold the "
        "feedback (0: always hold)", ge=0, le=10)
    stale_force_limit_n: float | None = param(
        None, unit="N", desc="stale-data policy: while the feedback is held on stale samples (after the predicted "
        "ones), |u - m*a_ref - u_learn| <= max(this, |u_ff|), u_ff the reference's friction feed-forward. None: "
        "the feed-forward's Coulomb (kinetic) level times its adapted scale: a sliding stage feels at least "
        "that friction and a stuck one needs the higher static level to break away, so a controller without "
        "data holds or slows down; inf (or no friction feed-forward and None): no limit", gt=0.0,
        allow_inf=True)


@dataclass
class ControllerState:
    """Diagnostics of the last step."""

    x_prev_m: float = math.nan
    v_hat_m_s: float = 0.0
    u_n: float = 0.0
    u_obs_prev_n: float = 0.0
    u_ff_n: float = 0.0
    u_inertia_n: float = 0.0
    d_hat_n: float = 0.0
    u_next_n: float = 0.0  # the predicted force of the period after the next one (predict_next_force)
    steps: int = 0
    terms: dict[str, float] = field(default_factory=dict)


def predict_next_force(u_n: float, ff_n: float, ff_prev_n: float, dt_s: float, period_s: float,
                       max_force_n: float) -> float:
    """The force the controller would command one period after ``u_n`` [N], for an actuator's command schedule
    (a slot the loop skips gets it instead of the held ``u_n``). Pure::

        û_{k+1} = clamp( u_k + (ff_k − ff_{k−1})·T/dt , ±max_force_n )

    ff = u_ff + m_ff·a_r(+look-ahead) + u_learn [N], the feed-forward (friction, inertia, learned), whose increment
    over the last sample interval ``dt_s`` [s] is extrapolated over one period ``period_s`` [s]; the feedback
    (PID + observer) is held: it needs the sample the skipped slot never takes, and extrapolating its
    increment extrapolates the sensor noise its derivative and observer carry. Over the seed stage's clean 1 kHz
    runs (10 µm cosine, 1 mm triangle) the RMS error of this prediction against the next command is 1.9 and 4.8 mN,
    against 5.0 and 11.3 mN for the held force and 3.3 and 5.5 mN for the linear extrapolation of the whole
    command; predicting the feedback by the mean of its last two values (1.4, 1.7 mN) made the skipped-slot
    runs of ``stagectl bench timing`` worse (cosine 3.0× → 4.0×, seed 1). Non-finite or dt ≤ 0: ``u_n``.
    """
    if not dt_s > 0.0:
        return u_n
    u = u_n + (ff_n - ff_prev_n) * (period_s / dt_s)
    if u - u != 0.0:
        return u_n
    return max(-max_force_n, min(max_force_n, u))


def resolve_model(cfg: ControllerConfig, file_model: StageModel | None = None) -> StageModel | None:
    """The stage model the feed-forward uses: inline ``friction`` > the (already loaded) ``model_file`` model,
    with the inline ``effects`` replacing the model's. Pure: reads no file.

    Parameters
    ----------
    cfg : ControllerConfig
    file_model : StageModel, optional
        ``feedforward.model_file`` as loaded by the configuration layer (None: no file).
    """
    ff = cfg.feedforward
    sm: StageModel | None = file_model
    if ff.friction is not None:
        mass = file_model.mass_kg if file_model is not None else None
        sm = StageModel(friction=ff.friction, mass_kg=mass)
    if sm is not None and ff.effects is not None:
        sm = StageModel(friction=sm.friction, effects=ff.effects, mass_kg=sm.mass_kg, meta=sm.meta)
    return sm


def _model_of(cfg: ControllerConfig, model: StageModel | FrictionModel | None) -> StageModel | None:
    """``model`` argument > ``feedforward.model`` (resolved by the loader) > inline ``friction``.

    Raises
    ------
    ConfigError
        ``feedforward.model_file`` is set but no resolved model came with it (the file is the loader's job).
    """
    if isinstance(model, FrictionModel):
        return StageModel(friction=model)
    if model is not None:
        return model
    ff = cfg.feedforward
    if ff.model is not None:
        return ff.model
    if ff.model_file is not None:
        raise ConfigError(f"controller.feedforward.model_file: {ff.model_file} is not loaded (load the "
                          "configuration with stagectl.config.load_app_config, or pass the StageModel)")
    return resolve_model(cfg, None)


def controller_mass(cfg: ControllerConfig, sm: StageModel | None) -> float | None:
    """The nominal moving mass [kg]: ``controller.mass_kg``, else the stage model's, else None."""
    if cfg.mass_kg is not None:
        return cfg.mass_kg
    return sm.mass_kg if sm is not None else None


def check_controller(cfg: ControllerConfig, model: StageModel | FrictionModel | None = None) -> list[str]:
    """What :class:`StageController` needs besides a valid ``cfg``: a model for ``feedforward.kind: model``
    and a mass (``mass_kg`` or the model's). Returns the problems (empty: the controller can be built); the
    configuration layer runs exactly this check, without designing the controller."""
    try:
        sm = _model_of(cfg, model)
    except ConfigError as exc:
        return list(exc.problems)
    problems: list[str] = []
    if cfg.feedforward.kind == "model" and sm is None:
        problems.append("controller.feedforward: kind 'model' needs friction:, model_file: or a model "
                        "from the application (or use kind: none / coulomb)")
    if controller_mass(cfg, sm) is None:
        problems.append("controller.mass_kg: required key missing kg (nominal moving mass; "
                        "or give mass_kg in the model file)")
    if cfg.rest_spring_rearm_m >= cfg.rest_spring_release_m:
        problems.append(f"controller.rest_spring_rearm_m: {cfg.rest_spring_rearm_m:g} m must be below "
                        f"rest_spring_release_m ({cfg.rest_spring_release_m:g} m)")
    return problems


#: the rest loop's gains (``rest_kd_fraction``, ``rest_dob_bandwidth_fraction``) act while the stage is held: at rest
#: with |v̂| <= REST_GAINS_ENTER_M_S for REST_GAINS_DWELL_S; the moving gains return at once when |v̂| exceeds
#: REST_GAINS_EXIT_M_S (the stage slips: the rest gains have less damping on a free mass) or the reference moves
REST_GAINS_ENTER_M_S = 1e-5
REST_GAINS_EXIT_M_S = 3e-5
REST_GAINS_DWELL_S = 0.005

#: the rest spring's stiffness test (``rest_spring_held_fraction``, :meth:`StageController._not_held`): the low-passed
#: position counts as reversed once it has turned back this far from its extreme [m] (the encoder's 1 nm steps and
#: 0.5 nm noise stay well below), and a branch is judged once, when it has run this many times that from the
#: reversal (the secant Σ(Δx·ΔF)/Σ(Δx²) over its first 10 nm)
REST_HELD_MIN_TRAVEL_M = 5e-9
REST_HELD_JUDGE_TRAVEL = 2.0
#: the stiffness test's first branch with no move since :meth:`StageController.reset` starts only after the witness
#: has run this many of its time constants 1/(2π·bandwidth) (its start-up transient, e.g. a stage found off its
#: last position at the reset, is no stiffness: a free mass started 20 nm off was judged 1.69·Σk "held")
REST_HELD_WARMUP_TIME_CONSTANTS = 5.0
#: before the stiffness test has judged a branch held, the full rest spring needs the stage to take a force,
#: |LPF(u − m·a)| (the witness; not within the witness's start-up after a reset), of at least this fraction of the
#: model's Coulomb level θ·F_c: a free mass takes none (a few mN of noise). 0.25 missed a stage held at 83 mN
#: (0.09·θ·F_c) after a settle move from ahead (model ×1.2: first step 131 ms instead of 16). (Also asking for the
#: stage to be still, |v̂| <= REST_GAINS_ENTER_M_S for 1 ms, delayed the spring at the first step of the bench's tuned
#: design, 14 -> 35 ms: the spring brakes a stage that slides on after its move.)
REST_HELD_FORCE_FRACTION = 0.05

#: without an observer the rest integral's total over a standstill is bounded by this many × θ·F_c (with one: 1):
#: a stage that slid on past the target at its sliding level comes back only through its whole pre-sliding
#: reversal, which takes up to twice that level (generated plant 29: 606 nm past, stuck at 158 nm with 1×)
REST_INTEGRAL_BOUND_X_NO_OBSERVER = 2.0
#: the rest integral (``rest_integral_hz``) acts once the stage no longer approaches the target: its speed towards
#: it, low-passed with this time constant [s], at most REST_INTEGRAL_STILL_M_S for REST_INTEGRAL_DWELL_S (a stage still
#: creeping in after its move is left to the moving loop: pushing it then slid it past the target, 190 nm behind to
#: 550 nm ahead; one creeping away, pushed by a position-dependent force such as cogging, is held back)
REST_INTEGRAL_VELOCITY_S = 0.01
REST_INTEGRAL_STILL_M_S = 2e-6
REST_INTEGRAL_DWELL_S = 0.02
#: ... and only outside this fraction of the in-position window (``settle.tolerance_m``). At 0.5 it pulled a stage
#: that had stopped 7 nm ahead, inside the 10 nm window, back to 5 nm before the next start, and the friction's small
#: reversal cost that start (generated plant 3 commissioned, lock-step: cosine 9.71 -> 11.19 nm RMS, its first
#: 0.1 s 17 -> 36 nm); at 0.8 the cosine is 9.71 nm with the steps unchanged (3/4 settled; plant 61 3/4, seed 100 4/4)
REST_INTEGRAL_DEADBAND = 0.8
#: ... on the soft side (the model's tangent stiffness towards the target below this fraction of Σk: the stage
#: stopped behind, its elements slipping) it ramps at the break-away gain instead (``_break_gain``), with the
#: model's break-away gap F_s − F_c taken as at least this fraction of F_c
REST_INTEGRAL_SOFT_FRACTION = 0.25
REST_INTEGRAL_GAP_MIN = 0.05
#: ... and only while the stage approaches the target at no more than this speed [m/s] (low-passed as above): a stage
#: still creeping in at 0.5 µm/s, pushed by 0.6 mN, broke away and slid 29 nm past the target (generated plant 34's
#: verification lead), which the next start paid (cosine 4.24 -> 5.59 nm RMS)
REST_INTEGRAL_SOFT_STILL_M_S = 2e-7

#: learning from earlier moves: weight of a move's normal equations per later move (memory ~1/(1 − 0.9) = 10
#: moves, so that a plant that changes is followed), and the prior weight (a fraction of the accumulated
#: information) towards the model as given
LEARN_FORGET = 0.9
#: the learners (adaptation, learning from moves) take an estimate as evidence only once the reference's inertia
#: force m·a_r and the stage's lag through the friction's spring θ·Σk·e have each moved by at most this fraction of
#: the model force (or its Coulomb level) over the last observer time constant (the signal against its low-pass at
#: the observer's bandwidth) ... (and a reversal is stiffness evidence for the adaptation only if there θ·Σk·|e|
#: was at most this fraction of the model force or its Coulomb level)
ADAPT_LAG_FRACTION = 0.1
#: the stop synchronisation's creep gate (:meth:`StageController._sync_creep`): a stage at rest that reaches
#: a new furthest point in the model's direction of travel, this far [m] beyond the last one counted (or the
#: end of the move), is sliding on: its friction elements are saturated in that direction, and the observer's
#: estimate then is the sliding level the plant has, not an unloaded pre-sliding state. The rest sync then
#: unloads the model (against that direction) only by what the estimate has dropped since the stage last slid
#: on (the force taken off a stage that then stuck unloads its springs without a visible travel: generated
#: plant 3, stuck 7 nm past its target with the feedback pulling back) plus θ·Σk times the stage's travel
#: back from its furthest point (a reversal: fresh k111, 150 nm back with 0.78 N). Unloaded anyway, the model
#: reloaded over the next move's first nanometres and pushed the stage ahead (generated plant 36
#: commissioned: the lead's stop crept 720 nm in; the cosine after it 3.5 -> 11.0 nm RMS with the rest sync,
#: 72 nm ahead at its start). Five sensor quanta of a 1 nm encoder, as REST_HELD_MIN_TRAVEL_M. Only without
#: the learning from moves (``feedforward.learn_moves_fraction`` 0, as commissioning writes): that learner
#: takes the sliding level into θ at each stop, from a move that starts with the estimate loaded into the
#: model (LEARN_START_FRACTION); with the gate it lost that evidence (bench control's 24 wrong-model draws,
#: the fourth step, a second −10 µm after a stop that slid on: 14-17 -> 19-34 ms)
SYNC_CREEP_M = 5e-9
#: ... and the observer's estimate it compares is low-passed with this time constant [s] (its sample-to-
#: sample noise, ±1 mN on plant 36 with a 130 Hz observer and a 1 nm encoder, is no drop of the force)
SYNC_CREEP_LPF_S = 0.02
# the stop synchronisation completed on a move's start edge (_sync_on_start): at most this many virtual steps of the
# model, until less than this fraction of the observer's estimate is left or a step moves less than that
SYNC_START_ITERATIONS = 12
SYNC_START_TOLERANCE = 0.02
#: ... for at least this many observer time constants in a row (the estimate has settled on the model's error)
ADAPT_SETTLED_TIME_CONSTANTS = 5.0
#: a sample interval longer than this many periods (a skipped slot, a stale sample before it) restarts that count:
#: the observer was not told the force the actuator applied in the slots it did not see, and its estimate carries
#: that force error for a few time constants, which is no error of the model
IRREGULAR_DT_PERIODS = 1.5
#: learning from earlier moves: the prior weight towards the model as given (a fraction of the accumulated
#: information; see LEARN_FORGET)
LEARN_RIDGE = 0.05
#: ... and the model's tangent stiffness is probed every this many cycles of a move
LEARN_TANGENT_EVERY = 2
#: confidence gates: a move is learned from only if the observer's estimate at its start is at most this fraction of
#: the RMS of its regressors (at rest the friction is indeterminate: an estimate the rest synchronisation has not yet
#: moved into the model is a mismatch of the model's *state*, which sliding erases, not an error of θ or β) ...
LEARN_START_FRACTION = 0.05
#: ... and only if it lasts at least this many observer time constants 1/(2π·dob.bandwidth_hz) (a shorter move's
#: estimate is mostly the observer's transient and timing, which the fit would take for θ and β)
LEARN_MIN_TIME_CONSTANTS = 15.0
#: ... and at least this long [s] whatever the observer's bandwidth: short moves bias the fit in β whatever the
#: observer (exact model, alternating moves at the default limits, 15 time constants only: 12 µm (21 ms) moves
#: walked β to 0.92 and 5-7 µm (15-18 ms) ones to 0.88 with a 150 Hz observer; 15 µm 0.96 at 100 and 150 Hz alike).
#: Just below 15 time constants at 100 Hz (23.9 ms), so a 100 Hz observer's gate is unchanged by it.
LEARN_MIN_MOVE_S = 0.0235
#: ... and only where its evidence is clear (docs/control.md §2.10). The baseline of a move's fit is the observer's
#: estimate at its start, d̂_0, and at rest that is ambiguous: a constant force keeps it through the move, a mismatch
#: of the model's pre-sliding *state* (what the stop's synchronisation has not yet moved into the model) is erased by
#: sliding. The fit with d̂_0 as baseline and the fit with 0 differ by Δp = d̂_0·A⁻¹·Σg (A, Σg: this move's normal
#: matrix and regressor sums); a move is learned from only if |Δθ| and |Δln β| are at most this (else the baseline
#: alone could move the model by more: the exact model after a 0.1 s rest was learned as θ 0.927) ...
LEARN_BASELINE_TOL = 0.01
#: ... and each parameter is updated only where the accumulated fit differs from its current value by more than
#: LEARN_SIGNIFICANCE standard errors (residuals of this move's fit, counted as one independent sample per two
#: observer time constants, since the estimate is low-passed by the observer). One standard error, not 2-3: the
#: 20 %-wrong model's first 10 µm step gives ln β 0.087 ± 0.042, and holding such first-move evidence back slowed
#: bench control's steps (3 SE: the config's third step 16 -> 19 ms; 1.5 SE: one of the 24 other wrong models'
#: steps 26 -> 31 ms). The standard error sees scatter, not a bias: the gates above are what keep transients and
#: the rest state out; this test keeps an exact model from following the noise of moves that carry little ...
LEARN_SIGNIFICANCE = 1.0
#: ... and one move changes θ, β by at most this fraction (a single move's evidence is bounded however clear)
LEARN_MAX_STEP = 0.25
#: observer anti-wind-up (``stuck_dob_fraction``): the stage counts as stuck while its speed between the last two
#: fresh samples is at most this fraction of the reference's speed
STUCK_SPEED_FRACTION = 0.25
#: ... and its evidence of a model that is too high (:meth:`StageController.stuck_excess_fraction`) forgets with
#: this time constant [s] of samples where the stage follows the reference
STUCK_EVIDENCE_TIME_S = 1.0
#: ... from samples after the stage has followed for at least this many observer time constants in a row (slips
#: of a stick-slip pass through "following" while the estimate is still wound up: not evidence)
STUCK_EVIDENCE_TIME_CONSTANTS = 5.0
#: the settle move from ahead's second continuation: its gain is the first's times the first's planned / measured
#: travel, bounded to [1/AHEAD_RATIO_MAX, AHEAD_RATIO_MAX] (docs/control.md §2.8: 1.2 / 1.3 / 1.4 give the worst step
#: of the seven models it changes most 29 / 28 / 33 ms; a travel still under way at τ = T misreads the stiffness)
AHEAD_RATIO_MAX = 1.3
#: peak |c̈|·T²/|e₀| of the rest-to-rest quintic (10/√3, at τ = T/2 ± T/(2√3)): the settle move's duration
#: for an inertial force budget (:meth:`StageController.settle_move_duration`)
QUINTIC_PEAK_ACCEL = 10.0 / math.sqrt(3.0)


@dataclass
class _MoveFit:
    """Least-squares normal equations for :meth:`StageController._learn_moves` (scalars only: real-time safe):
    those of the move under way (a··, b·) and those accumulated over the earlier moves (c··, r·). Regressors
    g = (∂u_ff/∂θ, ∂u_ff/∂ln β) and the spring correction pass the observer's first-order low-pass with one
    sample of delay (the observer's estimate lags the model error the same way); the measurement y is the
    observer's estimate against the model at the start of the move, plus the stage's friction spring over the
    tracking error."""

    rest: bool = True  # the reference was at rest at the last step
    valid: bool = False  # this move is learned from (no retune, no learned force during it)
    th0: float = 1.0  # θ at the start of the move
    b0: float = 1.0  # β at the start of the move
    f0: float = 0.0  # model force (θ = 1) at the start [N]
    d0: float = 0.0  # observer estimate at the start [N]
    x0: float = 0.0  # the model's fed position at the start [m]
    k_t: float = 0.0  # the model's tangent stiffness, last probed [N/m], and the direction it was probed in
    dir: int = 0
    g_th: float = 0.0  # the last raw regressors [N]
    g_b: float = 0.0
    f_th: float = 0.0  # filtered regressors [N]
    f_b: float = 0.0
    g_c: float = 0.0  # the friction spring over the tracking error, raw and filtered [N]
    f_c: float = 0.0
    a11: float = 0.0  # Σ f_th², Σ f_th·f_b, Σ f_b² [N²]; Σ f_th·y, Σ f_b·y [N²]; samples
    a12: float = 0.0
    a22: float = 0.0
    b1: float = 0.0
    b2: float = 0.0
    n: int = 0
    c11: float = 0.0  # the normal equations accumulated over the moves, in (θ, ln β) [N²]
    c12: float = 0.0
    c22: float = 0.0
    r1: float = 0.0
    r2: float = 0.0
    s1: float = 0.0  # Σ f_th, Σ f_b [N] (the baseline's leverage on the fit); Σ y² [N²] (residuals)
    s2: float = 0.0
    yy: float = 0.0
    se_th: float = math.inf  # standard errors of the last solve's (θ, ln β)
    se_u: float = math.inf
    n_all: int = 0  # samples of the move, used or not (its length)

    def start(self, th: float, b: float, f0: float, d0: float, x0: float) -> None:
        self.rest, self.valid = False, True
        self.th0, self.b0, self.f0, self.d0, self.x0 = th, b, f0, d0, x0
        self.dir = 0
        self.g_th = self.g_b = self.f_th = self.f_b = self.g_c = self.f_c = 0.0
        self.a11 = self.a12 = self.a22 = self.b1 = self.b2 = 0.0
        self.s1 = self.s2 = self.yy = 0.0
        self.n = self.n_all = 0

    def accumulate(self, a: float, g_th: float, g_b: float, y: float, c: float, use: bool = True) -> None:
        """One sample: the regressors' filters always step; the sums take it only if ``use`` (the stage follows)."""
        b = 1.0 - a
        f1 = a * self.f_th + b * self.g_th
        f2 = a * self.f_b + b * self.g_b
        fc = a * self.f_c + b * self.g_c
        self.f_th, self.f_b, self.f_c = f1, f2, fc
        self.g_th, self.g_b, self.g_c = g_th, g_b, c
        self.n_all += 1
        if not use:
            return
        y += fc
        self.a11 += f1 * f1
        self.a12 += f1 * f2
        self.a22 += f2 * f2
        self.b1 += f1 * y
        self.b2 += f2 * y
        self.s1 += f1
        self.s2 += f2
        self.yy += y * y
        self.n += 1

    def solve(self, min_force_n: float, samples_per_dof: float = 1.0) -> tuple[float, float] | None:
        """(θ, ln β): the least-squares fit over this move and the earlier ones (each earlier move's normal
        equations weighted by LEARN_FORGET per move since), about the model as given (θ = 1, β = 1) with a small
        prior weight; None when this move's model forces stayed below ``min_force_n`` (RMS): nothing learned
        from it."""
        n = self.n
        if n == 0 or self.a11 + self.a22 < n * min_force_n * min_force_n:
            return None
        if self.d0 * self.d0 * n > LEARN_START_FRACTION ** 2 * (self.a11 + self.a22):
            return None  # the move started from an estimate that is not a model error (LEARN_START_FRACTION)
        # this move's own fit (with a small ridge: β's regressor can be ~0) and how far its baseline d̂_0 moves it
        m11, m22, m12 = self.a11 * (1.0 + LEARN_RIDGE), self.a22 + LEARN_RIDGE * max(self.a22, LEARN_RIDGE * self.a11), \
            self.a12
        mdet = m11 * m22 - m12 * m12
        if not mdet > 0.0:
            return None
        dth = self.d0 * (m22 * self.s1 - m12 * self.s2) / mdet  # Δp = d̂_0·A⁻¹·Σg (LEARN_BASELINE_TOL)
        du = self.d0 * (m11 * self.s2 - m12 * self.s1) / mdet
        if abs(dth) > LEARN_BASELINE_TOL or abs(du) > LEARN_BASELINE_TOL:
            return None  # the start's estimate, model error or state mismatch, decides the fit: no evidence
        # residual variance of this move's fit (about its start), inflated by the samples per independent one
        q1, q2 = (m22 * self.b1 - m12 * self.b2) / mdet, (m11 * self.b2 - m12 * self.b1) / mdet
        sse = max(0.0, self.yy - 2.0 * (q1 * self.b1 + q2 * self.b2)
                  + q1 * q1 * self.a11 + 2.0 * q1 * q2 * self.a12 + q2 * q2 * self.a22)
        var = sse / max(1.0, n - 2.0) * max(1.0, samples_per_dof)
        # this move's equations A·(p − p0) = b about its start p0 = (θ0, ln β0), in absolute parameters
        u0 = math.log(self.b0)
        r1 = self.b1 + self.a11 * self.th0 + self.a12 * u0
        r2 = self.b2 + self.a12 * self.th0 + self.a22 * u0
        lam = LEARN_FORGET
        self.c11 = lam * self.c11 + self.a11
        self.c12 = lam * self.c12 + self.a12
        self.c22 = lam * self.c22 + self.a22
        self.r1 = lam * self.r1 + r1
        self.r2 = lam * self.r2 + r2
        # prior: LEARN_RIDGE of the accumulated information on each parameter, towards the model as given (1, 0);
        # also what keeps θ and β apart where they are nearly collinear (pre-sliding)
        # (on β at least LEARN_RIDGE² of θ's: a stiffness the moves say next to nothing about, as a static model's
        # whose tangent stiffness is ~0, stays at its prior instead of the ratio of two tiny sums)
        w1, w2 = LEARN_RIDGE * self.c11, LEARN_RIDGE * max(self.c22, LEARN_RIDGE * self.c11)
        a11, a22, a12 = self.c11 + w1, self.c22 + w2, self.c12
        det = a11 * a22 - a12 * a12
        if not det > 0.0:
            return None
        q1, q2 = self.r1 + w1 * 1.0, self.r2
        th, u = (a22 * q1 - a12 * q2) / det, (a11 * q2 - a12 * q1) / det
        # standard errors of the accumulated fit (its information scaled by this move's residual variance)
        self.se_th, self.se_u = math.sqrt(var * a22 / det), math.sqrt(var * a11 / det)
        return (th, u) if math.isfinite(th) and math.isfinite(u) else None


@dataclass
class _Parts:
    cfg: ControllerConfig
    mass_kg: float
    pid_cfg: PidConfig
    dob: QFilterDob | KalmanDob | None
    ff: FrictionFeedforward | CoulombFeedforward | None
    ff_rebuilt: bool
    dob_rebuilt: bool


class StageController:
    """PID + DOB + feed-forward (see module docstring).

    Parameters
    ----------
    cfg : ControllerConfig
    timing : Timing or float
        The loop's timing (or its nominal period [s]); discrete coefficients are derived for it once (and
        re-derived only if a step's ``dt`` differs).
    model : StageModel or FrictionModel, optional
        Model for ``feedforward.kind: model`` and the mass (takes precedence over ``feedforward.model``, the
        model the configuration loader resolved from ``friction:`` / ``model_file:``).

    Raises
    ------
    ConfigError
        No mass available, or ``kind: model`` without any model.
    """

    def __init__(self, cfg: ControllerConfig, timing: Timing | float,
                 model: StageModel | FrictionModel | None = None, *, plain_ff: bool = False) -> None:
        check_dt(timing.period_s if isinstance(timing, Timing) else timing)
        self.timing = Timing.of(timing)
        self.period_s = self.timing.period_s
        self._model_arg = model
        #: the model feed-forward steps as plain Python (no numba: a real stage's process), not compiled
        self.plain_ff = plain_ff
        self.state = ControllerState()
        self._pending: _Parts | None = None
        parts = self._build(cfg, None)
        self.cfg = cfg
        self.mass_kg = parts.mass_kg
        self.pid = Pid(cfg.pid)
        self.dob = parts.dob
        self.ff = parts.ff
        self.settle = SettleDetector(cfg.settle)
        self._vbeta = 0.0
        self._vdt = math.nan
        self._ff_ahead_s = 0.0  # time the feed-forward was advanced by hold() since the last step
        self._ref_stop = math.nan  # where the reference next rests without reversing [m] (set_reference_stop)
        self._pred_s = 0.0  # time covered by predicted steps (hold) since the last fresh sample
        self._gap = 0  # stale cycles since the last fresh sample
        self._f_kin = _kinetic_level(self.ff)  # the friction model's Coulomb level [N] (nan: no model)
        self._e_last = math.nan  # the last measured tracking error x_r − x [m]
        self._u_learn = 0.0  # the learned force in the last command [N]
        self.timing_scale = 1.0  # feedback slowed down by this factor (set_timing_scale)
        self.ff_scale = 1.0  # force scale θ of the friction feed-forward (feedforward.adapt_bandwidth_hz)
        self._k_ps = _stiffness(self.ff)  # the model's initial pre-sliding stiffness [N/m] (0: not known)
        # its elements (k_i, 2·W_i), largest friction force [N], linear reversal travel [m] (settle move from ahead)
        self._rev_el, self._f_max, self._rev_lin_m = _reversal_elements(self.ff)
        self._k_break = _break_gain(self.ff, self._k_ps, self._f_kin, cfg.rest_spring_range_m)  # [N/m]
        self._s_rest = 0.0  # low-passed rest spring force taken out of the observer's estimate [N]
        self._s_mid = 0.0  # first section of the rest spring's low-pass (rest_spring_section_count 2) [N]
        self._ml = _MoveFit()  # learning from earlier moves (feedforward.learn_moves_fraction)
        self._x_rest_m = math.nan  # reference where a move folded the rest spring, until adapt_presliding_m away [m]
        self._rs_armed = True  # the rest spring acts (False: released, the stage was seen not stuck)
        self._rs_releases = 0  # releases in this standstill
        self._rs_band_s = 0.0  # time within rest_spring_rearm_m since the release [s]
        self._rs_side = 0  # side of x − x_r beyond the hunting band (+1/−1; 0: not left it yet)
        self._rs_swings = 0  # sign changes of x − x_r across the hunting band since the spring was armed
        #: why the rest spring was last released at standstill: "slid", "hunting", "not held" ("" : not yet)
        self.rest_spring_release_reason = ""
        self.rest_spring_held_n_m = math.nan  # the last secant stiffness the stiffness test judged [N/m]
        self.rest_spring_release_count = 0  # releases at standstill since construction (telemetry, checks)
        self._hw = QFilterDob(cfg.dob, self.mass_kg, self.period_s)  # the stiffness test's force witness
        #: the force the actuator really gives [N] (set_actuator_limit; inf: max_force_n alone)
        self.actuator_limit_n = math.inf
        self._u_lim = cfg.max_force_n  # the output clamp L = min(max_force_n, actuator_limit_n) [N]
        self.reset(0.0)

    # ------------------------------------------------------------------ construction
    def _build(self, cfg: ControllerConfig, old: StageController | None) -> _Parts:
        problems = check_controller(cfg, self._model_arg)
        if problems:
            raise ConfigError(problems)
        ffc = cfg.feedforward
        same_ff = old is not None and same_friction_ff(old.cfg.feedforward, ffc)
        sm = _model_of(cfg, self._model_arg)
        mass = controller_mass(cfg, sm)
        if mass is None:  # excluded by check_controller
            raise ConfigError("controller.mass_kg: required key missing kg")
        # feed-forward
        ff: FrictionFeedforward | CoulombFeedforward | None
        kw = dict(reversal_threshold_m=ffc.reversal_threshold_m, reversal_velocity_m_s=ffc.reversal_velocity_m_s,
                  lookahead_s=self.period_s / 2.0 if ffc.lookahead_s is None else ffc.lookahead_s)
        if same_ff and old is not None:
            ff = old.ff
        elif ffc.kind == "model" and sm is not None:
            ff = FrictionFeedforward(sm.friction, sm.effects, plain=self.plain_ff, **kw)
        elif ffc.kind == "coulomb":
            eff = ffc.effects if ffc.effects is not None else Effects()
            ff = CoulombFeedforward(ffc.coulomb_n, ffc.viscous_n_s_m, eff, **kw)
        else:
            ff = None
        # observer
        dob: QFilterDob | KalmanDob | None
        dob_rebuilt = True
        if old is not None and old.dob is not None and old.cfg.dob.kind == cfg.dob.kind:
            dob = old.dob  # retuned at apply time (bumpless)
            dob_rebuilt = False
            if isinstance(dob, KalmanDob) and (old.cfg.dob != cfg.dob or old.mass_kg != mass):
                # design the new gain here (outside the loop), swap it in at apply time
                dob = KalmanDob(cfg.dob, mass, self.period_s)
                dob.state = old.dob.state
                dob_rebuilt = False
        else:
            dob = make_dob(cfg.dob, mass, self.period_s)
        return _Parts(cfg, mass, cfg.pid, dob, ff, not same_ff, dob_rebuilt)

    # ------------------------------------------------------------------ lifecycle
    def reset(self, x_m: float, u_n: float = 0.0) -> None:
        """Bumpless start at the measured position ``x_m`` [m]; the first output is ≈ ``u_n`` [N].

        Resets the integrator (preloaded with ``u_n``), the observer (d̂ = 0 at ``x_m``) and the
        feed-forward model (relaxed state at ``x_m``).
        """
        if not math.isfinite(x_m):
            raise ValueError(f"x_m must be finite (got {x_m})")
        if self._rest_gains:
            self._set_rest_gains(False)
        self._rg_still_s = 0.0  # the rest gains' dwell starts again
        self._sync_armed = False
        self._cr_n = 0  # the creep gate starts afresh
        self._cr_moved = 0.0
        self.pid.reset()
        self.pid.preload(u_n, 0.0)
        if self.dob is not None:
            self.dob.reset(x_m)
        self._hw.reset(x_m, u_n)
        self._h_xf = math.nan
        self._h_moved = False  # no move since the start: the stiffness test's first branch starts at the arming point
        self._h_age_s = 0.0  # time the witness has run since the reset [s]
        if self.ff is not None:
            self.ff.reset(x_m)
            if isinstance(self.ff, FrictionFeedforward):
                self.ff.input_scale = 1.0
        self.state = ControllerState(x_prev_m=x_m, u_n=u_n, u_obs_prev_n=u_n)
        self.settle.reset()
        self.ff_scale = 1.0
        self._ff_bump = None
        self._last_ref = None
        self._ff_ahead_s = 0.0
        self._ref_stop = math.nan
        self._pred_s = 0.0
        self._gap = 0
        self._e_last = math.nan
        self._x_fresh = x_m
        self._xr_fresh = math.nan
        self._dx_fresh = self._dxr_fresh = 0.0
        self._ev_num = self._ev_den = 0.0
        self._ev_dir = 0.0
        self._ev_run_s = 0.0
        self._ad_run_s = -1.0
        self._gate_shut = False
        self._rev_x, self._rev_ok = math.nan, True  # (the next reversal is judged afresh)
        self._u_learn = 0.0
        self._ml = _MoveFit()
        self._sm = SettleMove()  # settle move (settle.move_s)
        self._u_k = 0.0  # settle move from ahead: its spring force [N] (outside the observer's input)
        self._k_ahead = 0.0  # its gain γ·θ·β·Σk [N/m], set at its first sample
        self._tau_a = 0.0  # its look-ahead [s]
        self._ahead_pass = 0  # 0: none under way, 1: the first continuation from ahead, 2: the second
        self._ahead_ratio = 1.0  # the second's gain factor (planned / measured travel of the first, bounded)
        self._u_k_base = 0.0  # the first's force, held under the second [N]
        self._ahead_ks = 1.0  # the stiffness scale of the model's elements along the continuation (β, × the ratio)
        self._ahead_fs = 0.0  # the force scale γ·θ along it
        self._u_k_lo, self._u_k_hi = -math.inf, math.inf  # u_k's bounds: the model's friction range [N]
        self._reset_rest_spring()
        self._reset_rest_integral()

    def _reset_rest_integral(self) -> None:
        """The rest integral as at the start of a standstill: nothing added, not stopped, stillness not timed."""
        self._ri_n = 0.0  # force the rest integral has added in this standstill [N]
        self._ri_push = 0.0  # ... of it, the current push on the soft side (taken back at the break-away) [N]
        self._ri_i = 0.0  # ... without an observer: what of it the PID integrator still carries (not synchronised) [N]
        self._ri_still_s = 0.0  # time at rest with the low-passed speed <= REST_INTEGRAL_STILL_M_S [s]
        self._ri_v = 0.0  # the speed estimate low-passed over REST_INTEGRAL_VELOCITY_S [m/s]
        self._ri_off = False  # stopped for this standstill (the stage slid or hunted)
        self._ri_side = 0  # side of x_r − x beyond rest_spring_rearm_m (+1/−1; 0: not left it yet)
        self._ri_swings = 0  # sign changes of x_r − x across that band in this standstill

    def _reset_rest_spring(self) -> None:
        """The rest spring and its guard as at start (armed, no force, no swings or releases counted; no
        post-rest adaptation block): reset() and a retune, whose new settings rebuild the spring at rest."""
        self._s_rest = 0.0
        self._s_mid = 0.0
        self._x_rest_m = math.nan
        self._rs_armed = True
        self._rs_releases = 0
        self._rs_band_s = 0.0
        self._rs_side = 0
        self._rs_swings = 0
        self._reset_held()

    def _reset_held(self) -> None:
        """The stiffness test's regression afresh (the spring armed: a standstill's start, a re-arm)."""
        self._h_n = 0  # 0: not started since armed
        self._h_dir = 0  # direction of the stage's filtered travel (0: not yet REST_HELD_MIN_TRAVEL_M from the start)
        self._h_ext = self._h_fext = 0.0  # its extreme position [m] and the force there [N]
        self._h_rev = False  # a reversal seen: the branch from (x0, f0) is being measured
        self._h_x0 = self._h_f0 = 0.0
        self._h_sxx = self._h_sxf = 0.0  # Σ Δx² [m²], Σ Δx·ΔF [N·m] along the branch
        self._h_ok = False  # a branch of this standstill was judged held: the full spring acts
        self._h_load = False  # ... or the stage took a force a free mass cannot: the full spring acts as well

    def prepare_retune(self, new_cfg: ControllerConfig) -> _Parts:
        """Build what ``new_cfg`` needs (observer gain design, feed-forward model) without touching the loop."""
        return self._build(new_cfg, self)

    def request_retune(self, new_cfg: ControllerConfig) -> None:
        """Prepare now (caller's thread); the swap happens at the start of the next ``step``."""
        self._pending = self.prepare_retune(new_cfg)

    def retune(self, new_cfg: ControllerConfig) -> None:
        """Apply new settings now (call between steps), bumplessly.

        PID: the PID term keeps its value (integrator absorbs the gain change). Observer of the same kind:
        d̂ keeps its value. Observer switched off: its last d̂ moves into the integrator; switched on: it
        starts at d̂ = 0. Feed-forward changed (a key outside :data:`FF_LIVE_KEYS`): the new one starts relaxed
        at the current reference and the difference Δ (old − new force) moves into the observer's estimate
        (``dob.shift``) or, without an observer, into the integrator; else the running one (state, θ, β) goes on
        with the new live keys.
        """
        self._apply(self.prepare_retune(new_cfg))

    def _apply(self, parts: _Parts) -> None:
        st = self.state
        transfer = 0.0
        if self._s_rest != 0.0 and self.dob is not None:
            # fold the rest spring into the observer first (as at a move start): the new settings start from
            # the same d̂ and rebuild the spring at rest if they have one
            self.dob.shift(-self._s_rest)
            st.u_obs_prev_n -= self._s_rest
        self._reset_rest_spring()
        if self._u_k != 0.0:
            # a continuation from ahead under way: its force u_k (outside the observer's input) goes to the
            # observer now, as at its end (d̂ += u_k: u continuous; an observer switched off below hands it on to
            # the integrator), and the rest of the continuation runs without it
            if self.dob is not None:
                self.dob.shift(self._u_k)
                st.u_obs_prev_n += self._u_k
            else:  # (not reached: the continuation needs an observer)
                transfer += self._u_k
            self._u_k = self._u_k_base = 0.0
            self._ahead_pass = 0
            self._sm.stiff = False
        self._reset_rest_integral()  # (what it added stays in the observer / integrator, as any estimate)
        # the start-edge sync armed by the last standstill: only for the same model and observer, with the switch
        # still on (a retune that turns rest_sync_on_start off, or rebuilds the model, does not run it)
        self._sync_armed = (self._sync_armed and parts.cfg.feedforward.rest_sync_on_start and not parts.ff_rebuilt
                            and parts.dob is not None)
        if parts.ff_rebuilt:  # what was learned is about the old model
            self._ml = _MoveFit()
            self._cr_n = 0  # ... and so is the creep gate's count (its direction, what the sync unloaded)
        self._ml.rest, self._ml.valid = False, False  # a move under way when the settings change is not learned
        # observer
        old_dob = self.dob
        new_dob = parts.dob
        if old_dob is not None and new_dob is None:
            transfer += old_dob.state.d_hat_n
        elif new_dob is not None and parts.dob_rebuilt:
            d0 = 0.0
            if old_dob is not None:  # kind changed: keep d̂ continuous
                d0 = old_dob.state.d_hat_n
            x_now = st.x_prev_m if not math.isnan(st.x_prev_m) else 0.0
            new_dob.reset(x_now, d0)
            if isinstance(new_dob, QFilterDob):
                new_dob.state.v_hat_m_s = st.v_hat_m_s
        elif new_dob is not None and new_dob is not old_dob and isinstance(new_dob, KalmanDob):
            # prepared off-loop with the new gain; take over the running state and command history
            if isinstance(old_dob, KalmanDob):
                new_dob.take_over(old_dob)
        elif new_dob is not None:
            new_dob.retune(parts.cfg.dob, parts.mass_kg)  # Q-filter: cheap, bumpless
        # feed-forward
        if parts.ff_rebuilt:
            self._ff_bump = st.u_ff_n  # settled against the new feed-forward's first output in step()
            self.ff_scale = 1.0  # θ was learned for the old model (the bump above keeps u continuous)
            self._ev_num = self._ev_den = 0.0  # so was the anti-wind-up's evidence ε (_stuck_dob)
            if parts.ff is not None:
                ref_x = self._last_ref.x_m if self._last_ref is not None else st.x_prev_m
                parts.ff.reset(ref_x)
            st.u_ff_n = 0.0
        self._rest_gains = False  # the new settings start with their moving gains (a standstill switches again)
        self.pid.retune(_scaled_pid(parts.pid_cfg, self.timing_scale))
        if transfer:
            self.pid.preload(self.pid.state.u_pid_n + transfer)
        if parts.cfg.settle != self.cfg.settle:
            self.settle.cfg = parts.cfg.settle
        self.cfg = parts.cfg
        self._u_lim = min(parts.cfg.max_force_n, self.actuator_limit_n)
        self.mass_kg = parts.mass_kg
        m_hw = parts.mass_kg if parts.cfg.dob.nominal_mass_kg is None else parts.cfg.dob.nominal_mass_kg
        if parts.cfg.dob != self._hw.cfg or m_hw != self._hw.mass_kg:
            # the stiffness test's witness retuned in place, bumplessly, as the observer is (no allocation in
            # the cycle a requested retune lands in; its mass is the observer's nominal one when set)
            self._hw.retune(parts.cfg.dob, parts.mass_kg)
        self.dob = new_dob
        self.ff = parts.ff
        self._k_ps = _stiffness(parts.ff)
        self._rev_el, self._f_max, self._rev_lin_m = _reversal_elements(parts.ff)
        self._f_kin = _kinetic_level(parts.ff)
        self._k_break = _break_gain(parts.ff, self._k_ps, self._f_kin, parts.cfg.rest_spring_range_m)
        self._vdt = math.nan
        if self.timing_scale != 1.0 and isinstance(new_dob, QFilterDob):
            if new_dob.period_s is not None:  # (a rebuilt one has T: as set_timing_scale, s·T)
                new_dob.period_s = self.timing_scale * self.period_s
            new_dob.retune(_scaled_dob(parts.cfg.dob, self.timing_scale), parts.mass_kg)
        self._d_cfg = None  # _derive() again at the next step

    @property
    def force_limit_n(self) -> float:
        """The output clamp in force [N]: L = min(``max_force_n``, :attr:`actuator_limit_n`)."""
        return self._u_lim

    def set_actuator_limit(self, limit_n: float) -> None:
        """The largest force the actuator really applies [N] (a CiA 402 drive's max torque 0x6072 below
        ``max_force_n``: its driver clamps every command there; inf or not > 0: no limit of its own).

        The output clamp, the PID's saturation and anti-windup (conditional integration, |I| bound) and the
        observer's force input (the clamped command) then all use L = min(``max_force_n``, limit_n): the force
        actually available, so nothing winds up against a clamp the law cannot see. Kept across retunes."""
        lim = float(limit_n)
        self.actuator_limit_n = lim if lim > 0.0 and math.isfinite(lim) else math.inf
        self._u_lim = min(self.cfg.max_force_n, self.actuator_limit_n)

    def move_force_terms(self) -> tuple[float, float, float]:
        """What a planned move costs on this controller's model: (mass m [kg], static friction F_s [N], viscous
        F_v [N·s/m]), for planning moves within the usable force (:class:`~stagectl.control.trajectory.
        ForceBudget`). F_s is the model's largest friction force (max(F_s, F_c)), its Coulomb level where that
        is not known, 0 without a friction model; F_v its viscous coefficient (0 where not known)."""
        static = self._f_max if math.isfinite(self._f_max) else self._f_kin if math.isfinite(self._f_kin) else 0.0
        ff = self.ff
        if isinstance(ff, CoulombFeedforward):
            visc = float(ff.viscous_n_s_m)
        else:
            v = getattr(getattr(getattr(ff, "model", None), "params", None), "viscous_n_s_m", None)
            visc = float(v) if isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0 else 0.0
        return float(self.mass_kg), float(static), visc

    def set_reference_stop(self, x_m: float) -> None:
        """Where the reference next comes to rest without reversing first [m] (NaN: unknown), for the friction
        feed-forward's look-ahead at its next step or hold (:func:`stagectl.control.friction_ff.bounded_ahead`).
        The loop sets it each cycle from its reference source; without it the look-ahead is unbounded."""
        self._ref_stop = x_m

    def set_timing_scale(self, scale: float) -> None:
        """Slow the feedback down for a loop that runs slower than its period (real-time safe enough for a
        rare call: two bumpless retunes, no allocation beyond two small configs).

        ``scale`` s >= 1 is the effective sample interval over T (the loop's measure of skipped and late
        cycles). The crossover of the configured design is divided by s, so the margins it was designed with
        for T hold for a loop sampling at s·T: Kp/s², Ki/s³, Kd/s, derivative cut-off /s, Q-filter DOB
        bandwidth /s (a Kalman DOB is left as is), and the Q-filter's per-sample step designed for s·T (its
        ``period_s``, designed at once; on samples closer than s·T on average, the part of a step their mean
        span is: QFilterDob, "Irregular sampling"; with 30 % or 50 % of the slots skipped the 10 µm cosine
        tracked 6.5/5.5× and 4.2/6.7× the clean run, seeds 1/2, against 8.0/6.9× and 6.2/8.3× with T's).
        s = 1 restores the configured gains. The feed-forward is unchanged. Bumpless: the PID term and d̂ keep
        their values.
        """
        s = max(1.0, float(scale))
        if s == self.timing_scale:
            return
        self.timing_scale = s
        self._d_cfg = None  # _derive() again at the next step (the observer's decay)
        pc, dc = self._gains(self._rest_gains)
        self.pid.retune(_scaled_pid(pc, s))
        if isinstance(self.dob, QFilterDob):
            if self.dob.period_s is not None:  # one step of its filter per sample at the interval seen
                self.dob.period_s = s * self.period_s
            self.dob.retune(_scaled_dob(dc, s), self.mass_kg)

    def shift_observer(self, delta_n: float) -> None:
        """Move the observer's estimate d̂ by ``delta_n`` [N] between steps, with its input history and the
        controller's record of the observer's last and predicted inputs (``dob.shift``): the command steps by
        ``delta_n`` at the next step and the observer starts from the new estimate as its steady state. For
        a caller that knows the estimate is stale (the commissioning passes' start from a stuck stage,
        ``SpeedLadderFeedforward.release``). No observer: nothing."""
        if self.dob is None:
            return
        self.dob.shift(delta_n)
        self.state.u_obs_prev_n += delta_n

    _last_ref: Reference | None = None
    _h_f = 0.0  # the stiffness test's witness force LPF(u − m·a) [N] ...
    _h_xf = math.nan  # ... and filtered position [m]
    _h_moved = False  # the reference has moved since reset
    _h_ok = False  # the stiffness test judged a branch of this standstill held (the full rest spring acts)
    _h_load = False  # the stage took a force at standstill in this standstill (the full rest spring acts)
    _h_age_s = 0.0  # time the witness has run since the reset [s]
    _d_held = False
    _rest_gains = False  # the rest loop's gains are in force (rest_kd_fraction, rest_dob_bandwidth_fraction)
    _rg_still_s = 0.0  # time at rest with |v̂| <= REST_GAINS_ENTER_M_S [s]
    _x_fresh = math.nan  # the last fresh (measured, not predicted) position [m]
    _xr_fresh = math.nan  # the reference at the last fresh sample [m]
    _dx_fresh = 0.0  # the stage's travel between the last two fresh samples [m]
    _dxr_fresh = 0.0  # the reference's travel between the last two fresh samples [m]
    _ev_num = 0.0  # anti-wind-up evidence: forgetting sums of −d·d̂ and |u_ff| while the stage follows [N]
    _ev_den = 0.0
    _ev_dir = 0.0  # direction of the reference's current branch (0: at rest) ...
    _ev_run_s = 0.0  # time the stage has followed the reference, fresh samples in a row [s]
    _ev_x0 = 0.0  # ... and where it started [m]: evidence only beyond adapt_presliding_m of travel
    _ad_run_s = -1.0  # time since the reference's inertia force or the stage's lag last changed fast (the learners'
    # gate, _step; negative at rest) [s]
    _gate_shut = False  # an inertia transient shut the gate; it reopens once the lag has settled too
    _gate_a = 0.0  # the gate's low-passes of a_r [m/s²] and of the tracking error [m]
    _gate_e = 0.0
    _ff_bump: float | None = None
    _learn_active = False  # the last fresh step's learn_active (ILC takes part in the motion)
    _rev_x = math.nan  # the model's last reversal seen [m] ...
    _sync_armed = False  # the last step at rest ran the stop synchronisation: a move starting next completes it
    _d_creep = False
    _cr_n = 0  # the creep gate (_sync_creep): samples at rest since the reference stopped (0: moving) ...
    _cr_d = 0.0  # ... the model's direction of travel at the stop ...
    _cr_anchor = 0.0  # ... the stage's position at the last slide on (or the stop) and its furthest one
    # since [m] ...
    _cr_peak = 0.0
    _cr_slid = False  # ... whether it has slid on since the stop ...
    _cr_raw = 0.0  # ... the observer's estimate along d without the sync's loads (low-passed): now and at the
    # last slide on [N] ...
    _cr_raw_slide = 0.0
    _cr_moved = 0.0  # ... and the force the sync has unloaded the model by since the stop (along −d) [N]
    _cr_x = 0.0  # the stage's position at the last sample at rest [m]
    _rev_ok = True  # ... and whether the stage followed the reference there (its branch is stiffness evidence)

    def _adapt(self, dt: float, ref: Reference, u_ff: float, d_hat: float, dob: QFilterDob | KalmanDob,
               at_rest: bool) -> tuple[float, float]:
        """Feed-forward scale adaptation (module docstring): θ += γ·dt·d̂/F̂ while the reference moves,
        |F̂| >= ``adapt_min_force_n`` and no learned force is applied (one learner at a time: with ILC on, θ
        stays where it is); the force θ takes over leaves the observer (``dob.shift``): u unchanged."""
        ffc = self.cfg.feedforward
        th = self.ff_scale
        f_raw = u_ff / th
        if at_rest or abs(f_raw) < ffc.adapt_min_force_n:
            return u_ff, d_hat
        if self._ad_run_s * self._d_g < ADAPT_SETTLED_TIME_CONSTANTS:
            return u_ff, d_hat  # the reference's inertia force changed fast not long ago (_step): a transient
        if abs(ref.x_m - self._x_rest_m) < ffc.adapt_presliding_m:
            # the first adapt_presliding_m after a move started with the rest spring folded into the observer:
            # the observer still carries that force, not an error of the model's scale or stiffness
            return u_ff, d_hat
        lo, hi = 1.0 - ffc.adapt_max_change_fraction, 1.0 + ffc.adapt_max_change_fraction
        gam = 2.0 * math.pi * ffc.adapt_bandwidth_hz
        ff = self.ff
        if ffc.adapt_presliding_m > 0.0 and isinstance(ff, FrictionFeedforward):
            fst = ff.state
            if abs(fst.x_fed_m - fst.x_rev_m) < ffc.adapt_presliding_m:
                if not self._rev_ok:
                    return u_ff, d_hat  # the stage was off the reference at the reversal: not evidence (_step)
                # within adapt_presliding_m of the last reversal the model error is its stiffness: β, the scale
                # of the model's input, takes it (dβ/dt = γ·β·d̂/(θ·ΔF̂), ΔF̂ = F̂ − F̂ at the reversal); the
                # force level θ is left alone
                df = ff.model_force_n - fst.f_rev_n  # both the model's own friction force (no effects)
                if abs(df) >= 0.5 * ffc.adapt_min_force_n:
                    b = ff.input_scale
                    ff.input_scale = min(hi, max(lo, b + gam * dt * d_hat / (th * df) * b))
                return u_ff, d_hat
        return self._set_theta(min(hi, max(lo, th + gam * dt * d_hat / f_raw)), f_raw, d_hat, dob)

    def _set_theta(self, th_new: float, f_raw: float, d_hat: float,
                   dob: QFilterDob | KalmanDob) -> tuple[float, float]:
        """θ := ``th_new`` bumplessly: the old − new feed-forward force (θ − θ_new)·F̂ [N] moves into the
        observer (``dob.shift``), so u is unchanged; returns the new (u_ff, d̂)."""
        delta = (self.ff_scale - th_new) * f_raw  # old − new feed-forward force: the observer carries it from now
        self.ff_scale = th_new
        dob.shift(delta)
        return th_new * f_raw, d_hat + delta

    def _learn_moves(self, dt: float, ff: FrictionFeedforward, u_ff: float, d_hat: float,
                     dob: QFilterDob | KalmanDob, at_rest: bool, learning: bool,
                     e_m: float) -> tuple[float, float]:
        """Learning from earlier moves (``feedforward.learn_moves_fraction`` = κ; module docstring): while the
        reference moves, accumulate the least-squares normal equations of the model's error at the reference
        against its sensitivities to θ and ln β (:class:`_MoveFit`); when it comes to rest, move θ and β the
        fraction κ towards the fit over this and the earlier moves (θ bumplessly: the force it takes leaves the
        observer; β changes only the model's next increments). Real-time safe (scalars; two probe steps of the
        model every other moving cycle for its tangent stiffness)."""
        ml = self._ml
        th = self.ff_scale
        f_raw = u_ff / th
        if not at_rest:
            if ml.rest:  # a move starts: the model and observer as they were at rest are the baseline (the model
                # force of the last step: this step's has already moved, by all of its jump for a static model);
                # the estimate as the loop goes on from it, without the rest spring's force that _rest_spring folds
                # into the observer below
                ml.start(th, ff.input_scale, self.state.u_ff_n / th, d_hat - self._s_rest, ff.state.x_fed_m)
            if learning:  # the learner (ILC) is active for this motion: one learner at a time
                ml.valid = False
            if not ml.valid:
                return u_ff, d_hat
            fst = ff.state
            g_th = f_raw - ml.f0  # ∂u_ff/∂θ since the start of the move [N]
            # the branch: from the last reversal or, if later, the start of this move (the standstill's rest sync
            # has re-loaded the model's elements there)
            x_b = fst.x_rev_m if (fst.x_rev_m - ml.x0) * fst.direction > 0.0 else ml.x0
            if ml.n % LEARN_TANGENT_EVERY == 0 or fst.direction != ml.dir:
                # the model's tangent stiffness changes smoothly along a move: probed every other cycle (two model
                # steps; the moving step costs 7.3 instead of 5.3 µs hot, 8.4 µs probing every cycle)
                ml.k_t = ff.tangent_n_m(fst.direction) if fst.direction else 0.0
                ml.dir = fst.direction
            k_t = ml.k_t
            g_b = th * (fst.x_fed_m - x_b) * k_t
            y = d_hat + (th - ml.th0) * f_raw - ml.d0  # the estimate against the model at the start of the move
            a = self._dob_decay(dt)
            # the stage's own friction spring over the tracking error e is in the estimate (F(x) = F(x_r) − k·e):
            # added back, through the observer's filter, so that y is the model's error at the reference
            # only samples a few observer time constants after the reference's inertia force last changed fast
            # (the same gate as _adapt's, _step): a move's acceleration transient is not evidence
            ml.accumulate(a, g_th, g_b, y, th * k_t * e_m, self._ad_run_s * self._d_g >= ADAPT_SETTLED_TIME_CONSTANTS)
            return u_ff, d_hat
        if ml.rest:
            return u_ff, d_hat
        ml.rest = True
        # (the time constants counted over the samples the gate let through: evidence, not just duration)
        long_enough = (ml.n * self.period_s * 2.0 * math.pi * self.cfg.dob.bandwidth_hz / self.timing_scale
                       >= LEARN_MIN_TIME_CONSTANTS and ml.n_all * self.period_s >= LEARN_MIN_MOVE_S)
        g_dob = 2.0 * math.pi * self.cfg.dob.bandwidth_hz / self.timing_scale
        per_dof = 2.0 / (g_dob * self.period_s)  # samples per independent one: two observer time constants
        fit = ml.solve(self.cfg.feedforward.adapt_min_force_n, per_dof) if ml.valid and long_enough else None
        if fit is None:
            return u_ff, d_hat
        ffc = self.cfg.feedforward
        k = ffc.learn_moves_fraction
        lo, hi = 1.0 - ffc.adapt_max_change_fraction, 1.0 + ffc.adapt_max_change_fraction
        step = LEARN_MAX_STEP
        th_new = th
        if abs(fit[0] - th) > LEARN_SIGNIFICANCE * ml.se_th:  # significant: the evidence says θ is wrong
            th_new = min(hi, max(lo, th + max(-step, min(step, k * (fit[0] - th)))))
        b = ff.input_scale
        if abs(fit[1] - math.log(b)) > LEARN_SIGNIFICANCE * ml.se_u:
            beta = math.exp(min(math.log(hi), max(math.log(lo), fit[1])))  # ln β bounded first: exp cannot overflow
            ff.input_scale = min(hi, max(lo, b + max(-step * b, min(step * b, k * (beta - b)))))
        if th_new == th:
            return u_ff, d_hat
        return self._set_theta(th_new, f_raw, d_hat, dob)

    def _settle_move(self, dt: float, ref: Reference, x_m: float, v_hat: float,
                     ilc: bool) -> tuple[Reference, float]:
        """Settle move (``settle.move_s``; :mod:`stagectl.control.settle_move`): at the first sample at rest after
        a move, with an observer, a model feed-forward and no ILC taking part, a stage behind the reference in the
        move's direction by more than ``settle.move_min_m`` (None: ``rest_spring_range_m``) starts the
        continuation c from e₀ = x_r − x, ė₀ = −v̂. Returns the feedback's reference (x_r − c, v_r − ċ, a_r − c̈)
        and the continuation's time τ at this step [s] (nan: none; the inertia term adds −m·c̈(τ + τ_a))."""
        sm = self._sm
        if sm.observe(ref[1], ref[2]) and self._d_settle and not ilc:  # (_derive: move_s > 0, DOB, model FF)
            scfg = self.cfg.settle
            e0 = ref.x_m - x_m
            e_min = scfg.move_min_m if scfg.move_min_m is not None else self.cfg.rest_spring_range_m
            if sm.direction * e0 > e_min:
                sm.start(e0, -v_hat, self.settle_move_duration(e0))
            elif (sm.direction * e0 < -e_min and sm.last_direction == sm.direction
                  and scfg.ahead_stiffness_fraction > 0.0 and self._k_ps > 0.0):
                # ahead (the stiff side): the same continuation, with the reversal's spring force (_step)
                sm.start(e0, -v_hat, self.settle_move_duration(e0))
                sm.stiff = True
        if not sm.active and sm.stiff and self._ahead_pass == 1 and ref[1] == 0.0 and ref[2] == 0.0:
            # the continuation from ahead has ended: one more from where the stage is, if it is off by more than
            # half of move_min_m, its gain scaled by the travel measured on the first (see _step)
            e = ref.x_m - x_m
            scfg = self.cfg.settle
            e_min = scfg.move_min_m if scfg.move_min_m is not None else self.cfg.rest_spring_range_m
            if abs(e) > 0.5 * e_min:
                e_first = sm.e0
                travel = e_first - e  # the first continuation's measured travel (planned: e_first)
                ratio = e_first / travel if travel * e_first > 0.0 else AHEAD_RATIO_MAX
                self._ahead_ratio = min(AHEAD_RATIO_MAX, max(1.0 / AHEAD_RATIO_MAX, ratio))
                self._u_k_base = self._u_k
                sm.start(e, -v_hat, self.settle_move_duration(e))
                sm.stiff = True
                self._ahead_pass = 2
        if not sm.active:
            return ref, math.nan
        tau = sm.tau_s
        c, cd, cdd = sm.sample(tau)
        sm.tau_s = tau + dt
        if sm.tau_s > sm.duration_s + 1e-9 * dt:
            sm.active = False
        return Reference(ref.x_m - c, ref.v_m_s - cd, ref.a_m_s2 - cdd), tau

    def settle_move_duration(self, e0_m: float) -> float:
        """The settle move's duration T [s] for an error ``e0_m`` [m] at the end of a move: the shortest T >=
        ``settle.move_s`` whose rest-to-rest quintic needs at most ``settle.move_force_n`` of inertial force,
        m·|c̈|max = m·(10/√3)·|e₀|/T² <= F, i.e. T = max(move_s, √(10/√3·m·|e₀|/F)) (m: the inertia
        feed-forward's mass); ``move_s`` alone without ``move_force_n``."""
        scfg = self.cfg.settle
        f = scfg.move_force_n
        if f is None:
            return scfg.move_s
        ffc = self.cfg.feedforward
        m = ffc.mass_kg if ffc.mass_kg is not None else self.mass_kg
        return max(scfg.move_s, math.sqrt(QUINTIC_PEAK_ACCEL * m * abs(e0_m) / f))

    def _stuck_dob(self, dt: float, ref: Reference, x_m: float, u_ff: float, d_hat: float,
                   dob: QFilterDob | KalmanDob) -> float:
        """Observer anti-wind-up against the friction feed-forward (module docstring): while the reference moves
        in direction d, is ahead of the stage (d·(x_r − x) > 0), the stage is measured stuck (its travel between
        the last two fresh samples <= STUCK_SPEED_FRACTION × the reference's, not the filtered velocity) and the
        feed-forward pushes along d, the estimate may cancel at most the model's own uncertainty of it plus the
        excess the stage was seen not to need while it followed: d·d̂ >= −(δ + ε)·|u_ff| (δ =
        ``stuck_dob_fraction``, ε = :meth:`stuck_excess_fraction`). An estimate beyond it is returned towards the
        bound at the observer's rate (excess ×(1 − a) per step, a = min(exp(−2π·f_DOB/s·dt), the Q filter's decay
        in this step, :meth:`_dob_decay`): at least as fast as the filter winds it on, also in a loop slowed down
        on on-time samples or with skipped ones; no step in u. ``dob.shift`` moves the observer's state with it. Fresh steps while the stage follows
        the reference update ε first."""
        v_r = ref.v_m_s
        d = 1.0 if v_r > 0.0 else -1.0 if v_r < 0.0 else 0.0
        if d == 0.0 or d * u_ff <= 0.0:
            return d_hat
        ffc = self.cfg.feedforward
        if d != self._ev_dir:  # a new branch: the motion starts or reverses here
            self._ev_dir, self._ev_x0 = d, ref.x_m
        dx, dxr = d * self._dx_fresh, abs(self._dxr_fresh)
        g = self._d_g  # the observer's rate 2π·f_DOB/s [1/s] (s: timing scale; 1 for a Kalman DOB: not slowed)
        if self._gap == 0:
            if (d * self._dxr_fresh > 0.0 and d * u_ff >= ffc.adapt_min_force_n
                    and d * (ref.x_m - self._ev_x0) >= ffc.adapt_presliding_m
                    and abs(dx - dxr) <= STUCK_SPEED_FRACTION * dxr):
                self._ev_run_s += dt
            else:
                self._ev_run_s = 0.0
            if self._ev_run_s * g >= STUCK_EVIDENCE_TIME_CONSTANTS:
                # the stage has followed (within ±25 % of the reference's travel) for a few observer time
                # constants: its friction is the sliding one and the estimate has settled on it, so the estimate's
                # share of the feed-forward is the model's error there (−d·d̂ > 0: the model is too high)
                lam = math.exp(-dt / STUCK_EVIDENCE_TIME_S)
                self._ev_num = lam * self._ev_num - d * d_hat
                self._ev_den = lam * self._ev_den + abs(u_ff)
        if d * (ref.x_m - x_m) <= 0.0 or abs(dx) > STUCK_SPEED_FRACTION * dxr:
            return d_hat
        # at least at the observer's designed rate and at least at the rate its filter moved this step (a Q filter
        # with a period P, stepped on a span h < P: 1 − (1 − a_P)·h/P; a P-step on a span h > P): the estimate never
        # winds on beyond the bound faster than it is brought back (on time the two are the same value)
        a = math.exp(-g * dt)
        if self._d_g_scaled:
            a = min(a, self._dob_decay(dt))
        bound = -(self.cfg.stuck_dob_fraction + self.stuck_excess_fraction()) * abs(u_ff)
        ps = self.pid.state
        if d * ps.i_n < 0.0 and d * (d_hat + ps.i_n) < bound:
            # the PID integrator wound against the motion too (while the stage stood ahead of the reference) and,
            # with the estimate, cancels more of the feed-forward than the bound allows: it goes back towards 0
            # at the same rate
            ps.i_n *= a
        excess = bound - d * d_hat
        if excess <= 0.0:
            return d_hat
        delta = d * (1.0 - a) * excess
        dob.shift(delta)
        return d_hat + delta

    def stuck_excess_fraction(self) -> float:
        """ε >= 0: the share of the friction feed-forward the observer took back while the stage last followed a
        moving reference (Σ −d·d̂ / Σ |u_ff| over fresh samples with the stage's travel within ±25 % of the
        reference's and |u_ff| >= ``adapt_min_force_n`` along the motion, forgetting time
        STUCK_EVIDENCE_TIME_S): how much too high the (adapted) model is where its friction is determinate;
        0 for a model that is too low. inf before any such sample: the bound waits for evidence (a model too
        high can keep the stage from ever following steadily, and then the bound would lock its excess in)."""
        return max(0.0, self._ev_num / self._ev_den) if self._ev_den > 0.0 else math.inf

    def _rest_sync(self, dt: float, ff: FrictionFeedforward, u_ff: float, d_hat: float,
                   dob: QFilterDob | KalmanDob) -> tuple[float, float]:
        """Feed-forward through the stop: move λ·d̂ (λ = 1 − exp(−2π·rest_sync_hz·dt)) of the observer's estimate
        into the model's state by a virtual displacement Δx = λ·d̂/(θ·k_ps) (k_ps: the model's largest,
        initial pre-sliding stiffness, so the step never overshoots; |Δx| <= rest_sync_max_step_m). Whatever
        force the model really takes (ΔF, less once its elements saturate) leaves the observer: u unchanged."""
        ffc = self.cfg.feedforward
        k = self._k_ps
        if k <= 0.0 or d_hat == 0.0:
            return u_ff, d_hat
        th = self.ff_scale
        lam = 1.0 - math.exp(-2.0 * math.pi * ffc.rest_sync_hz * dt)
        lim = ffc.rest_sync_max_step_m
        dx = max(-lim, min(lim, lam * d_hat / (th * k)))
        dx = self._creep_limited(dx)
        if dx == 0.0:
            return u_ff, d_hat
        new = th * ff.nudge(dx, dt)
        delta = u_ff - new  # old − new feed-forward force: the observer carries it
        self._cr_moved += self._cr_d * delta
        dob.shift(delta)
        return new, d_hat + delta

    def _sync_creep(self, dt: float, at_rest: bool, x_m: float, d: float, d_hat: float) -> None:
        """The stop synchronisation's creep gate (SYNC_CREEP_M): at each sample with the reference at rest (a
        settle move included: the stage's travel back along it is a reversal, not a slide on) the stage's
        position ``x_m`` [m] against its furthest one in the model's direction of travel ``d`` (at the stop)
        since the reference stopped, and the observer's estimate ``d_hat`` [N] without what the sync moved
        into the model (low-passed over SYNC_CREEP_LPF_S); a motion of the reference starts it afresh."""
        if not at_rest:
            self._cr_n = 0
            self._cr_moved = 0.0
            return
        raw = (self._cr_d * d_hat - self._cr_moved) if self._cr_n else d * d_hat
        if self._cr_n:  # (low-passed over SYNC_CREEP_LPF_S: the estimate's sample noise is no drop)
            b = math.exp(-dt / SYNC_CREEP_LPF_S)
            raw = b * self._cr_raw + (1.0 - b) * raw
        self._cr_raw = raw
        if self._cr_n == 0:
            self._cr_d = d
            self._cr_anchor = self._cr_peak = x_m
            self._cr_slid = False
            self._cr_moved = 0.0
        else:
            d = self._cr_d
            if d * (x_m - self._cr_peak) >= 0.0:
                self._cr_peak = x_m
                if d * (x_m - self._cr_anchor) > SYNC_CREEP_M:  # a new furthest point: sliding on
                    self._cr_anchor = x_m
                    self._cr_slid = True
                    self._cr_raw_slide = raw
        self._cr_x = x_m
        self._cr_n += 1

    def _creep_limited(self, dx: float) -> float:
        """The rest sync's virtual displacement ``dx`` [m] within the creep gate (SYNC_CREEP_M): once
        the stage has slid on in the model's direction d since the stop, a displacement against d
        (unloading the model) is limited so that the force unloaded since the stop stays within what
        the observer's estimate has dropped since the stage last slid on, max(0, d̂_slide − d̂) along
        d, plus θ·Σk times its own travel back from its furthest point beyond SYNC_CREEP_M (a
        reversal; θ·Σk per metre of virtual travel, the model's largest stiffness); else unchanged. A
        displacement along d is never limited."""
        d = self._cr_d
        if self._cr_n == 0 or d * dx >= 0.0 or not self._cr_slid or not self._d_creep:
            return dx
        k = self.ff_scale * self._k_ps
        # the force dropped since the last slide on and the stage's own travel back from its furthest point (a
        # reversal, through the model's largest stiffness): each is evidence of springs unloaded
        back = max(0.0, d * (self._cr_peak - self._cr_x) - SYNC_CREEP_M)
        room = max(0.0, self._cr_raw_slide - self._cr_raw) + k * back - self._cr_moved
        if room <= 0.0 or k <= 0.0:
            return 0.0
        return -d * min(abs(dx), room / k)

    def _sync_on_start(self, dt: float, ff: FrictionFeedforward, dob: QFilterDob | KalmanDob,
                       direction: float = 0.0) -> None:
        """The stop synchronisation completes on a move's start edge (module docstring, "Feed-forward through the
        stop"): the standstill before it synchronised (:meth:`_rest_sync` ran at its last sample), and whatever of
        the observer's estimate d̂ [N] it has not yet loaded into the model (at most ``rest_sync_max_step_m`` of
        virtual travel per period: after a short dwell most of it) is loaded now, before the model takes the
        move's first step along the reference, if it is more than one period of the rest sync can load
        (θ·Σk·rest_sync_max_step_m: after a long enough standstill nothing changes). Without it a move that starts with a reversal begins from the
        model's state of the previous direction while the observer still holds the force the stage really has:
        the model's reversal swings the feed-forward by up to 2·F_c, the observer's old level stays on top, and
        the stage is pushed ahead of the reference (a 30 ms dwell: 5.3 µm ahead; README "Move and settle").

        The same virtual displacements as the rest sync's, Δx = d̂/(θ·Σk) each (Σk the largest, initial stiffness:
        no step overshoots), at the rest sync's largest virtual speed rest_sync_max_step_m/T (the model's σ1 and
        viscous terms stay as small as in the standstill's own steps), at most SYNC_START_ITERATIONS of them and
        until less than SYNC_START_TOLERANCE of d̂ is left or a step moves less than that; the force the model
        takes leaves the observer (``dob.shift``, and the observer's last input with it: u unchanged). Real-time
        safe (scalars; at most SYNC_START_ITERATIONS model steps, once per move).

        ``direction`` (+1 / −1, 0: unknown) is the starting move's: one that goes on in the stop's
        direction after the stage crept on loads within the creep gate (:meth:`_creep_limited`,
        SYNC_CREEP_M: the plant's springs are not unloaded, and an unloaded model would reload over
        the first nanometres and push the stage ahead); a reversal loads all of it (the plant's branch
        starts at the force the stage holds, the model's should)."""
        st = self.state
        delta = self._load_into_model(dt, ff, st.d_hat_n, creep_gate=direction * self._cr_d > 0.0)
        if delta != 0.0:
            self.shift_observer(delta)
            st.d_hat_n += delta
            st.u_ff_n -= delta

    def _start_edge(self, dt: float, ff: FrictionFeedforward, dob: QFilterDob | KalmanDob | None,
                    settling: bool, direction: float = 0.0) -> None:
        """A move's start edge (the first step, fresh or held, with the reference moving) after a standstill whose
        stop synchronisation was under way (``_sync_armed``), or during a settle move from ahead (``settling`` with
        the continuation's ``stiff``): the continuation's reversal spring force u_k goes to the observer first
        (d̂ += u_k: no step in u) and the ahead pass ends; then the synchronisation completes
        (:meth:`_sync_on_start` towards ``direction``'s sign, without an observer
        :meth:`_sync_on_start_integral`). Disarms the sync."""
        st = self.state
        if settling and self._sm.stiff and dob is not None:
            if self._u_k != 0.0:
                self.shift_observer(self._u_k)
                st.d_hat_n += self._u_k
                self._u_k = 0.0
            self._ahead_pass = 0
            self._sm.stiff = False
            self._sync_on_start(dt, ff, dob)
        elif self._sync_armed and not settling:
            if dob is None:  # (armed by the rest integral's own synchronisation, _rest_sync_integral)
                self._sync_on_start_integral(dt, ff)
            else:
                self._sync_on_start(dt, ff, dob, direction)
        self._sync_armed = False

    def _load_into_model(self, dt: float, ff: FrictionFeedforward, force_n: float,
                         creep_gate: bool = False) -> float:
        """The start-edge load shared by :meth:`_sync_on_start` and :meth:`_sync_on_start_integral`: steps the
        model by Δx = rem/(θ·Σk) at the rest sync's largest virtual speed rest_sync_max_step_m/T, at most
        SYNC_START_ITERATIONS times, until less than SYNC_START_TOLERANCE of ``force_n`` [N] (what the observer
        or the rest integral still holds) is left or a step moves less than that. Returns δ [N], the old
        feed-forward force minus the new one (the caller's holder takes it, u unchanged); 0 when ``force_n`` is
        no more than one period of the rest sync can load (θ·Σk·rest_sync_max_step_m: the sync converged)."""
        k = self._k_ps
        th = self.ff_scale
        ffc = self.cfg.feedforward
        if k <= 0.0 or th <= 0.0 or not abs(force_n) > th * k * ffc.rest_sync_max_step_m:
            return 0.0
        v_v = ffc.rest_sync_max_step_m / self.period_s  # the rest sync's largest virtual speed [m/s]
        u_old = u_ff = th * ff.state.u_ff_n
        rem = force_n
        for _ in range(SYNC_START_ITERATIONS):
            dx = rem / (th * k)
            if creep_gate:
                dx = self._creep_limited(dx)
                if dx == 0.0:
                    break
            new = th * ff.nudge(dx, max(dt, abs(dx) / v_v) if v_v > 0.0 else dt)
            moved = u_ff - new  # old − new feed-forward force: the holder carries it
            if creep_gate:
                self._cr_moved += self._cr_d * moved
            u_ff = new
            rem += moved
            tol = SYNC_START_TOLERANCE * abs(force_n)
            if abs(rem) <= tol or abs(moved) <= tol:
                break
        return u_old - u_ff

    def _rest_sync_where(self, ff: FrictionFeedforward, x_r: float, x_m: float, v_hat: float) -> bool:
        """Where the stop synchronisation loads the model (module docstring, "Feed-forward through the stop"):
        within ``rest_spring_range_m`` of the reference at x_r, as fed; with the stage stuck further *ahead* of x_r
        (in the model's direction of travel; |v̂| <= REST_GAINS_ENTER_M_S) at the stage's position x: the model is
        fed there
        (:meth:`FrictionFeedforward.feed_at`), so the next move's reference travel up to the stage, which the
        stuck stage does not make, leaves the model's state alone; with the stage further *behind*, or still
        sliding, not at all (and the model fed at x_r again, if an earlier period fed it at the stage ahead: the
        stage has left that position). Returns whether to synchronise this period."""
        e = x_r - x_m
        d = ff.latch.direction
        if d * e < 0.0 and abs(e) > self.cfg.rest_spring_range_m and abs(v_hat) <= REST_GAINS_ENTER_M_S:
            ff.feed_at(x_m)
            return True
        if d * (ff.state.x_fed_m - x_r) > 0.0:  # fed at the stage (ahead) before it came back or moved off
            ff.feed_at(x_r)
        return abs(e) <= self.cfg.rest_spring_range_m

    def _rest_integral(self, dt: float, e_m: float, v_hat: float, d_hat: float) -> float:
        """Rest integral (``rest_integral_hz`` = f_r; module docstring): one step at standstill of a still stage,
        δ = 2π·f_r·k_r·clamp(e, ±rest_spring_range_m)·dt with k_r = min(θ, 1)·Σk, the total over the standstill
        bounded by θ·F_c; δ goes into the observer's estimate (``dob.shift``: the observer takes it as applied,
        so it does not integrate it again). Returns d̂ [N]."""
        cfg = self.cfg
        if self._ri_off:
            return d_hat
        band = cfg.rest_spring_rearm_m
        if abs(e_m) > band:
            side = 1 if e_m > 0.0 else -1
            if self._ri_side != 0 and side != self._ri_side:
                self._ri_swings += 1
            self._ri_side = side
        if abs(e_m) > cfg.rest_spring_release_m or self._ri_swings >= 2:
            self._ri_off = True  # the stage slides or hunts: it is not held stuck (as the rest spring's guard)
            return d_hat
        b = math.exp(-dt / REST_INTEGRAL_VELOCITY_S)
        v_lp = self._ri_v = b * self._ri_v + (1.0 - b) * v_hat
        if (v_lp * e_m > REST_INTEGRAL_STILL_M_S * abs(e_m)
                and (self._ri_n == 0.0 or self._ri_push != 0.0)):
            # still creeping in towards the target: the move's own settling, not a stuck stage (a stage creeping away
            # from it is what the integral is for). Once the integral has acted on the stiff side in this
            # standstill, the stage's approach is its own doing and it goes on: waiting REST_INTEGRAL_DWELL_S after
            # each of its increments made it act a quarter of the time (a stage stuck 300 nm ahead still 100 nm
            # off after 0.25 s, generated plant 36)
            self._ri_still_s = 0.0
            push = self._ri_push
            if push != 0.0:
                # a push on the soft side broke the stage away: it is taken back at once (bumpless for the
                # observer, a step of the push in u), so that the stage slides only as far as the force took it
                # past its break-away level, sticks again short of or near the target and is pushed anew
                # (stick-slip positioning in small increments; kept, the push slid it past the target)
                self._ri_push = 0.0
                return self._ri_add(-push, d_hat)
            return d_hat
        self._ri_still_s += dt
        if self._ri_still_s < REST_INTEGRAL_DWELL_S or abs(e_m) <= REST_INTEGRAL_DEADBAND * cfg.settle.tolerance_m:
            # inside 0.8 of the in-position window there is nothing to finish: pulling a stage back by a few nm
            # there leaves its friction at a small reversal the model does not know, which the next start pays
            # (a cosine from rest after 6 nm taken back: 7.4 -> 11.8 nm RMS)
            return d_hat
        r = cfg.rest_spring_range_m
        ff = self.ff
        if not isinstance(ff, FrictionFeedforward):  # (excluded by _derive)
            return d_hat
        # the model's stiffness for moving the stage on towards the reference from the state it holds: Σk on the
        # stiff side (the stage stopped ahead: its elements unload), ~0 on the soft side (behind: they already slip,
        # and a push breaks the stage away and slides it past the target)
        k_r = min(self.ff_scale, 1.0) * max(0.0, ff.tangent_n_m(1 if e_m > 0.0 else -1))
        if k_r < REST_INTEGRAL_SOFT_FRACTION * min(self.ff_scale, 1.0) * self._k_ps:
            # the soft side (the stage stopped behind, its elements at their slip limit): no spring to act
            # through, the stage moves on only once the force passes its break-away level. Ramp towards it at
            # the break-away gain k_b = min(Σk, ΔF_b/r) (ΔF_b the model's break-away gap F_s − F_c, at least
            # REST_INTEGRAL_GAP_MIN·F_c): at |e| = r the gap is covered in one time constant 1/(2π·f_r). Once
            # the stage moves towards the target the still gate above stops the ramp and takes the push back
            if self._ri_v * e_m > REST_INTEGRAL_SOFT_STILL_M_S * abs(e_m):
                return d_hat  # still creeping in, however slowly: a push would break it away into a slide
            k_r = max(k_r, min(self.ff_scale, 1.0) * self._k_break)
            soft = True
        else:
            soft = False
        delta = 2.0 * math.pi * cfg.rest_integral_hz * k_r * max(-r, min(r, e_m)) * dt
        bound = self.ff_scale * self._f_kin if self._f_kin == self._f_kin else self._u_lim
        if self.dob is None:
            # without an observer nothing else moves the stuck stage: one that slid on past the target at its
            # sliding level is taken back only through its whole reversal, up to twice the level (Masing's rule)
            bound *= REST_INTEGRAL_BOUND_X_NO_OBSERVER
        total = max(-bound, min(bound, self._ri_n + delta))
        delta = total - self._ri_n
        if delta == 0.0:
            return d_hat
        # on the stiff side a push still outstanding from the soft side (the stage slid past the target before the
        # still gate saw it approach) is kept in the total and only forgotten as a push: the stage stuck where it
        # took it, its elements loaded by it, and taking it back at once would spring the stage back through Σk by
        # up to push/Σk (0.16 N on the seed stage: ~250 nm, for a 60 nm overshoot; taken back as soon as the stage
        # was seen past the target, the closed-loop case of tests/control/test_rest_integral.py sprang back from
        # 1 nm past to 17 nm short). The stiff side's integral unwinds it in proportion to the error instead, and
        # the approach back is not paused (the stiff side's approach is its own doing, above)
        self._ri_push = self._ri_push + delta if soft else 0.0
        return self._ri_add(delta, d_hat)

    def _ri_add(self, delta: float, d_hat: float) -> float:
        """Add ``delta`` [N] to the rest integral's force: into the observer's estimate (``dob.shift``, taken as
        applied), or without an observer into the PID integrator. Returns d̂ [N]."""
        self._ri_n += delta
        dob = self.dob
        if dob is None:
            self.pid.state.i_n += delta
            self._ri_i += delta
            return d_hat
        dob.shift(delta)
        self.state.u_obs_prev_n += delta
        return d_hat + delta

    def _sync_on_start_integral(self, dt: float, ff: FrictionFeedforward) -> None:
        """:meth:`_sync_on_start` without an observer: on a move's start edge after a standstill whose rest
        integral's synchronisation (:meth:`_rest_sync_integral`) was under way, what of the rest integral's force R
        (``_ri_i``, in the PID integrator) it has not yet loaded into the model is loaded now, in the same virtual
        displacements Δx = R/(θ·Σk), and leaves R and the integrator (u unchanged). Without it the integrator
        carried R into the move, where the PID's integrator unwinds it only at K_i·e (fresh k105: R = −0.53 N
        against a move forward at F_c = 0.85 N left the stage stuck 9 µm behind for 0.3 s, and the next move
        back slid it 47 µm past: a following-error fault). Real-time safe (at most SYNC_START_ITERATIONS model
        steps, once per move)."""
        delta = self._load_into_model(dt, ff, self._ri_i)
        if delta != 0.0:
            self._ri_i += delta
            self.pid.state.i_n += delta
            self.state.u_ff_n -= delta

    def _rest_sync_integral(self, dt: float, ff: FrictionFeedforward, u_ff: float) -> float:
        """The stop synchronisation without an observer (``feedforward.rest_sync_hz`` with ``rest_integral_hz``):
        as :meth:`_rest_sync`, but of the rest integral's own force R (in the PID integrator, which also carries
        what it integrated in the move): Δx = λ·R/(θ·k_ps), |Δx| <= rest_sync_max_step_m, and the force the model
        takes leaves both R and the integrator (u unchanged). The next move then starts with the force that
        holds the stage in the model's pre-sliding state, which sliding unloads as it does the plant's, instead
        of in the integrator, where it stayed into the move. Returns u_ff [N]."""
        r = self._ri_i
        k = self._k_ps
        if k <= 0.0 or r == 0.0:
            return u_ff
        ffc = self.cfg.feedforward
        th = self.ff_scale
        lam = 1.0 - math.exp(-2.0 * math.pi * ffc.rest_sync_hz * dt)
        lim = ffc.rest_sync_max_step_m
        dx = max(-lim, min(lim, lam * r / (th * k)))
        new = th * ff.nudge(dx, dt)
        delta = u_ff - new
        self._ri_i += delta
        self.pid.state.i_n += delta
        return new

    def _rest_spring(self, dt: float, ref: Reference, x_m: float, d_hat: float, at_rest: bool,
                     dob: QFilterDob | KalmanDob) -> float:
        """Rest spring (module docstring): at standstill d̂ := d̂ − s, s = LPF_g(k_v·clamp(x − x_r)); at the
        start of a move, and when |x − x_r| leaves ``rest_spring_release_m`` or the stage hunts (it is not stuck), s is folded
        into the observer (d̂ and its input history move by −s: u continuous) and the spring is released; it is
        re-armed (s = k_v·(x − x_r), the observer moved by +s: u continuous) once |x − x_r| stayed within
        ``rest_spring_rearm_m`` for ``rest_spring_rearm_s``, at most ``rest_spring_max_release_count`` − 1 times per
        standstill; a move re-arms it."""
        if not at_rest:
            self._h_moved = True
        if (not at_rest and self._s_rest == 0.0 and self._rs_armed and self._rs_side == 0 and self._rs_swings == 0
                and self._rs_releases == 0):
            # moving with the spring armed and empty, nothing counted: what the code below leaves, the stiffness
            # test's branch included (a standstill's test starts afresh: an extreme kept from the last standstill
            # turned the stage's own run-in at a stop into a "reversal" and released a held stage, "not held")
            if self._h_n != 0 or self._h_ok or self._h_load:
                self._reset_held()
            return d_hat
        cfg = self.cfg
        e_x = x_m - ref.x_m
        r = cfg.rest_spring_range_m
        band = cfg.rest_spring_rearm_m
        if at_rest and self._rs_armed and abs(e_x) > band:
            side = 1 if e_x > 0.0 else -1
            if self._rs_side != 0 and side != self._rs_side:
                self._rs_swings += 1
            self._rs_side = side
        kv = cfg.rest_stiffness_fraction * min(self.ff_scale, 1.0) * self._k_ps  # θ capped at 1: docstring
        not_held = at_rest and self._rs_armed and self._d_held and self._not_held(kv, ref.x_m)
        if self._d_held and not self._h_ok:  # not (yet) seen held: the free-mass level (docstring, "Rest spring")
            if at_rest and self._rs_armed and not self._h_load and (self._h_moved or self._h_age_s >= self._h_warm_s()):
                f_c = self._f_kin if self._f_kin == self._f_kin else 0.0
                self._h_load = abs(self._h_f) >= REST_HELD_FORCE_FRACTION * min(self.ff_scale, 1.0) * f_c > 0.0
            if not self._h_load:
                kv = min(kv, cfg.rest_spring_unconfirmed_kp_fraction * self.pid.cfg.kp_n_m)
        if not at_rest or (self._rs_armed and (abs(e_x) > cfg.rest_spring_release_m or self._rs_swings >= 2
                                               or not_held)):
            self._rs_side = 0
            self._rs_swings = 0
            self._reset_held()
            if at_rest:
                self.rest_spring_release_reason = ("slid" if abs(e_x) > cfg.rest_spring_release_m else
                                                   "not held" if not_held else "hunting")
                self.rest_spring_release_count += 1
                self._rs_armed = False
                self._rs_releases += 1
                self._rs_band_s = 0.0
            else:
                self._rs_armed = True
                self._rs_releases = 0
            s = self._s_rest
            self._s_mid = 0.0
            if s != 0.0:
                self._s_rest = 0.0
                dob.shift(-s)
                return d_hat - s
            return d_hat
        if not self._rs_armed:
            if self._rs_releases >= cfg.rest_spring_max_release_count or abs(e_x) > band:
                self._rs_band_s = 0.0
                return d_hat
            self._rs_band_s += dt
            if self._rs_band_s + 1e-9 * dt < cfg.rest_spring_rearm_s:
                return d_hat
            # re-arm bumplessly: the spring starts at its steady force, which the observer takes over first
            self._rs_armed = True
            self._reset_held()
            s = kv * max(-r, min(r, e_x))
            self._s_rest = self._s_mid = s
            dob.shift(s)
            return d_hat
        target = kv * max(-r, min(r, e_x))
        a = self._dob_decay(dt)
        if cfg.rest_spring_section_count == 2:
            self._s_mid = a * self._s_mid + (1.0 - a) * target
            target = self._s_mid
        self._s_rest = a * self._s_rest + (1.0 - a) * target
        return d_hat - self._s_rest

    def _h_warm_s(self) -> float:
        """The witness's start-up time after a reset [s]: REST_HELD_WARMUP_TIME_CONSTANTS of its low-pass."""
        return REST_HELD_WARMUP_TIME_CONSTANTS / (2.0 * math.pi * self._hw.cfg.bandwidth_hz)

    def _not_held(self, kv: float, x_r: float) -> bool:
        """The rest spring's stiffness test (``rest_spring_held_fraction`` = ρ; module docstring, "Rest spring"):
        the force the stage takes, F = LPF(u − m·a) (the witness observer), against its position x_f = LPF(x) along
        the branch since the stage's last reversal (x_f turned back by REST_HELD_MIN_TRAVEL_M from its extreme; a
        pre-sliding contact is at its stiffest there, Σk on the plant the model describes). True once the branch has
        run REST_HELD_MIN_TRAVEL_M·REST_HELD_JUDGE_TRAVEL and its secant stiffness k̂ = Σ(Δx·ΔF)/Σ(Δx²) (Δ from the
        reversal) is below ρ/φ·k_v = ρ·min(θ, 1)·Σk [N/m]: the stage is not held by a spring stiffer than the rest
        spring needs. With no move since :meth:`reset` the branch from the arming point is judged as well (the
        contact's history is unknown). After a move a stage that approaches the target without turning back is not
        judged (its elements may slip: it arrives on its soft side), nor a branch whose
        judging point (10 nm from its reversal) lies beyond ``rest_spring_range_m`` of the reference ``x_r`` [m] (the
        spring's force is clamped there: a bounded force, not a stiffness of the loop)."""
        xf, f = self._h_xf, self._h_f
        h = REST_HELD_MIN_TRAVEL_M
        if self._h_n == 0:  # armed: look for the first extreme from here
            if not self._h_moved and self._h_age_s < self._h_warm_s():
                return False  # the witness's start-up transient is no stiffness
            self._h_n, self._h_dir, self._h_ext, self._h_fext = 1, 0, xf, f
            self._h_sxx = self._h_sxf = 0.0
            if not self._h_moved:  # no move since the start: the contact's history is unknown, a branch starts here
                self._h_rev = True
                self._h_x0, self._h_f0 = xf, f
            return False
        d = self._h_dir
        if d == 0:
            if abs(xf - self._h_ext) >= h:
                self._h_dir = 1 if xf > self._h_ext else -1
                self._h_ext, self._h_fext = xf, f
            if not self._h_rev:
                return False
            # no move since the start: the first branch runs from the arming point, whatever x_f does, until it is
            # judged (its extreme follows x_f); from then on the extreme stays put, so that the direction is found
            # once x_f has left it by h and a later reversal starts a new branch (before, none was ever seen)
            if self._h_sxx >= 0.0:
                self._h_ext, self._h_fext = xf, f
        elif (xf - self._h_ext) * d >= 0.0:  # still going on: a new extreme
            self._h_ext, self._h_fext = xf, f
            if not self._h_rev or self._h_sxx < 0.0:
                return False
        elif not self._h_rev or (self._h_ext - xf) * d >= h:
            if (self._h_ext - xf) * d >= h:  # turned back: a reversal, a new branch starts at the extreme
                self._h_rev = True
                self._h_x0, self._h_f0 = self._h_ext, self._h_fext
                self._h_sxx = self._h_sxf = 0.0
                self._h_dir = -d
                self._h_ext, self._h_fext = xf, f
            else:
                return False
        if self._h_sxx < 0.0:  # this branch was judged
            return False
        dx, df = xf - self._h_x0, f - self._h_f0
        self._h_sxx += dx * dx
        self._h_sxf += dx * df
        if abs(dx) < h * REST_HELD_JUDGE_TRAVEL:
            return False
        cfg = self.cfg
        r = cfg.rest_spring_range_m
        if abs(xf - x_r) > r:
            # beyond the spring's range its force is clamped (a bounded force, no stiffness of the loop): not judged
            self._h_sxx = -1.0
            return False
        k_min = cfg.rest_spring_held_fraction / cfg.rest_stiffness_fraction * kv
        self.rest_spring_held_n_m = k_hat = self._h_sxf / self._h_sxx
        self._h_sxx = -1.0  # judged once, at its start: further on a pre-sliding contact softens as its elements slip
        if k_hat < k_min:
            self._h_ok = False
            return True
        self._h_ok = True
        return False

    # ------------------------------------------------------------------ loop
    #: the loop may pass the learned feed-forward (``u_learn_n``) to :meth:`step`
    accepts_learned_force = True

    def step(self, dt: float, x_meas_m: float, ref: Reference, u_learn_n: float = 0.0,
             learn_active: bool = False) -> Command:
        """One control step on a fresh sample (real-time safe). Raises ``ValueError`` on bad dt or non-finite
        inputs.

        ``dt`` [s] is the time since the previous fresh sample; stale cycles in between that :meth:`hold` stepped
        on a predicted position are taken off it. ``u_learn_n`` [N]: a learned feed-forward force added to the
        command (ILC); the observer counts it as applied, so it does not estimate it away. ``learn_active``:
        the learner (ILC) takes part in this motion — armed and recording (its first repetition applies
        nothing) or applying; with it, or with u_learn_n ≠ 0, neither the adaptation nor the learning from
        moves changes θ, β (one learner at a time)."""
        if not (dt > 0.0 and dt < math.inf):
            check_dt(dt)
        if x_meas_m - x_meas_m != 0.0:  # nan unless finite
            raise ValueError(f"x_meas_m must be finite (got {x_meas_m})")
        # the stage's and the reference's travel between fresh samples (predicted steps move with x_r): their
        # ratio is the stuck test's, free of dt (after a gap longer than the loop's dt cap, Δx/dt overstates
        # the speed)
        x_f, xr_f = self._x_fresh, self._xr_fresh
        x_r = ref[0]
        self._dx_fresh = 0.0 if x_f != x_f else x_meas_m - x_f
        self._dxr_fresh = ref[1] * dt if xr_f != xr_f else x_r - xr_f
        self._x_fresh = x_meas_m
        self._xr_fresh = x_r
        if self._pred_s:
            rest = dt - self._pred_s
            self._pred_s = 0.0
            if rest > 1e-6 * dt:
                dt = self.period_s if abs(rest - self.period_s) <= 1e-6 * self.period_s else rest
        self._gap = 0
        self._learn_active = learn_active  # the predicted steps of hold() keep the last fresh step's
        cmd = self._step(dt, x_meas_m, ref, u_learn_n, learn_active or u_learn_n != 0.0)
        self._e_last = x_r - x_meas_m
        return cmd

    def next_force_increment_n(self) -> float:
        """û_{k+1} − u_k [N]: the predicted change of the force one period after the last step's or hold's
        command (:func:`predict_next_force`; feedback held, feed-forward extrapolated). The loop adds it to the
        force it writes, so a learned force added outside or a safety clamp keep their share."""
        st = self.state
        return st.u_next_n - st.u_n

    def stale_force_limit(self) -> float:
        """Half-width L [N] of the stale-data force band about m·a_ref + u_learn (see :meth:`hold`):
        max(``stale_force_limit_n`` or else θ·F_c, |u_ff|) (F_c: the feed-forward's Coulomb level, θ its adapted
        scale, u_ff the last friction feed-forward); inf without a limit and without a friction level."""
        lim = self.cfg.stale_force_limit_n
        if lim is None:
            lim = self.ff_scale * self._f_kin if self._f_kin == self._f_kin else math.inf
        return max(lim, abs(self.state.u_ff_n))

    def _stale_limit(self, u: float, terms: dict[str, float]) -> Command:
        """A held cycle's force ``u`` [N] limited to the stale-data band (:meth:`hold`); the state (and so the
        observer's next input and the next held cycle) takes the limited force."""
        st = self.state
        lim = self.stale_force_limit()
        c = st.u_inertia_n + self._u_learn
        if c - lim <= u <= c + lim:
            return Command(u, terms, ("stale",))
        u = c + lim if u > c else c - lim
        st.u_n = st.u_next_n = u  # (the limited force is held, so is its schedule)
        st.u_obs_prev_n = u - st.u_ff_n - self._u_k
        return Command(u, terms, ("stale", "stale_force"))

    _d_cfg: ControllerConfig | None = None  # the settings, observer and feed-forward _derive() was run for
    _d_dob: object = None
    _d_ff: object = None
    _a_dt = math.nan  # dt (or the observer's period) of the cached observer decay _a_val (_dob_decay)
    _d_q_period = False
    _a_val = 0.0

    def _derive(self) -> None:
        """What the step needs from the settings, looked up once per change of them (of ``cfg``, the observer,
        the feed-forward or the timing scale) instead of every cycle: which features act, the inertia mass."""
        cfg = self.cfg
        ffc = cfg.feedforward
        dob, ff = self.dob, self.ff
        self._d_cfg, self._d_dob, self._d_ff = cfg, dob, ff
        model_ff = isinstance(ff, FrictionFeedforward)
        self._d_vcut = cfg.velocity_cutoff_hz
        self._d_m_ff = (ffc.mass_kg if ffc.mass_kg is not None else self.mass_kg) if ffc.inertia else 0.0
        self._d_stuck = dob is not None and ff is not None and cfg.stuck_dob_fraction != math.inf
        self._d_learn = ffc.learn_moves_fraction > 0.0 and dob is not None and model_ff
        self._d_adapt = ffc.adapt_bandwidth_hz > 0.0 and dob is not None and ff is not None
        self._d_spring = dob is not None and cfg.rest_stiffness_fraction > 0.0 and self._k_ps > 0.0
        self._d_held = self._d_spring and cfg.rest_spring_held_fraction > 0.0
        self._d_sync = ffc.rest_sync_hz > 0.0 and dob is not None and model_ff
        # the creep gate (SYNC_CREEP_M) without the learning from moves only: that learner takes a sliding
        # level into θ at each stop, and only from a move that starts with the estimate loaded into the model
        self._d_creep = self._d_sync and ffc.learn_moves_fraction == 0.0
        self._d_rest_int = cfg.rest_integral_hz > 0.0 and model_ff and self._k_ps > 0.0
        # without an observer the rest integral acts through the PID integrator, and the stop synchronisation hands
        # the force it found (only that) to the model's state (_rest_sync_integral)
        self._d_ri_sync = self._d_rest_int and dob is None and ffc.rest_sync_hz > 0.0
        self._d_hold = dob is not None and cfg.hold_integrator_at_rest
        self._d_rest_gains = isinstance(dob, QFilterDob) and (cfg.rest_kd_fraction != 1.0
                                                              or cfg.rest_dob_bandwidth_fraction != 1.0)
        s = self.timing_scale if isinstance(dob, QFilterDob) else 1.0  # a Kalman DOB is not slowed down
        self._d_g = 2.0 * math.pi * cfg.dob.bandwidth_hz / s  # the observer's rate [1/s] (_stuck_dob)
        self._d_g_scaled = s == self.timing_scale  # exp(−g·dt) is _dob_decay(dt)
        self._d_q_period = isinstance(dob, QFilterDob) and dob.period_s is not None  # _dob_decay: P's steps
        scfg = cfg.settle
        self._d_settle = scfg.move_s > 0.0 and dob is not None and model_ff  # a settle move may start
        self._a_dt = math.nan

    def _dob_decay(self, dt: float) -> float:
        """a: the observer's decay in this step at its current bandwidth f_DOB/s (s: the timing scale), for the
        filters matched to it (the stuck-stage limit, the rest spring, the learners' filters). A Q-filter observer
        with a period P (s·T) steps its filter once per sample, P's or the part f = h/P of it for a shorter span
        (QFilterDob, "Irregular sampling"): a = a_P = exp(−2π·f_DOB/s·P), or 1 − (1 − a_P)·f, whatever ``dt``
        [s]; else exp(−g·dt), g the observer's rate of :meth:`_derive` (2π·f_DOB/s; a Kalman observer is not
        slowed down: 2π·f_DOB). a_P, exp(−g·dt), are computed once per P, dt (cached until the settings change:
        :meth:`_derive`)."""
        dob = self.dob
        if self._d_q_period and isinstance(dob, QFilterDob) and dob.period_s is not None:
            p = dob.period_s
            if p != self._a_dt:
                self._a_dt = p
                self._a_val = math.exp(-2.0 * math.pi * self.cfg.dob.bandwidth_hz / self.timing_scale * p)
            f = dob.step_fraction
            return self._a_val if f == 1.0 else 1.0 - (1.0 - self._a_val) * f
        if dt != self._a_dt:
            self._a_dt = dt
            self._a_val = math.exp(-self._d_g * dt)
        return self._a_val

    def _gains(self, rest: bool) -> tuple[PidConfig, DobConfig]:
        """The PID and observer settings in force (before the timing scale): the configured ones, or at rest those
        with ``rest_kd_fraction`` and ``rest_dob_bandwidth_fraction`` applied (module docstring, "Rest loop")."""
        cfg = self.cfg
        if not rest:
            return cfg.pid, cfg.dob
        return (dataclasses.replace(cfg.pid, kd_n_s_m=cfg.pid.kd_n_s_m * cfg.rest_kd_fraction),
                dataclasses.replace(cfg.dob, bandwidth_hz=cfg.dob.bandwidth_hz * cfg.rest_dob_bandwidth_fraction))

    def _set_rest_gains(self, rest: bool) -> None:
        """Switch to the rest loop's gains or back (at a standstill's start and end; bumpless: the PID term and d̂
        keep their values, as in a retune; two small configs allocated per switch).

        K_d changes by rescaling the derivative filter's state, ė_f ← ė_f·K_d,old/K_d,new: D = K_d·ė_f is continuous
        and its value decays with the filter (1/(2π·f_c), 1.6 ms) as it would have. Left to the retune's preload,
        the step (K_d,new − K_d,old)·ė_f went into the integrator for good — ė_f at rest is the 1 nm encoder's
        quantisation noise (±700 nm/s), a 0.1-0.2 mN step in I on the first sample of the move, which the loop
        removes only at the PI zero's rate (K_i/K_p ≈ 13 s⁻¹: 80 ms), the stage 2-4 nm ahead into the break-away:
        the 10 µm cosine's error after a 0.3 s rest was 3.64 nm RMS with the rest gains, 2.33 without."""
        self._rest_gains = rest
        pc, dc = self._gains(rest)
        s = self.timing_scale
        pid = self.pid
        kd_old, kd_new = pid.cfg.kd_n_s_m, pc.kd_n_s_m / s
        if kd_new > 0.0:
            pid.state.deriv_m_s *= kd_old / kd_new
        pid.retune(_scaled_pid(pc, s))
        if isinstance(self.dob, QFilterDob):
            self.dob.retune(_scaled_dob(dc, s), self.mass_kg)

    def _step(self, dt: float, x_meas_m: float, ref: Reference, u_learn_n: float, ilc: bool) -> Command:
        x_r, v_r, a_r = ref
        if (x_r - x_r) + (v_r - v_r) + (a_r - a_r) != 0.0:  # nan unless all three are finite
            raise ValueError(f"reference must be finite (got {ref})")
        pend = self._pending
        if pend is not None:
            self._pending = None
            self._apply(pend)
        cfg = self.cfg
        ff = self.ff
        dob = self.dob
        if cfg is not self._d_cfg or dob is not self._d_dob or ff is not self._d_ff:
            self._derive()
        st = self.state
        # velocity estimate
        x_prev = st.x_prev_m
        v_raw = 0.0 if x_prev != x_prev else (x_meas_m - x_prev) / dt
        vcut = self._d_vcut
        if vcut is None:
            v_hat = v_raw
        else:
            if dt != self._vdt:
                self._vdt = dt
                self._vbeta = math.exp(-2.0 * math.pi * vcut * dt)
            vb = self._vbeta
            v_hat = vb * st.v_hat_m_s + (1.0 - vb) * v_raw
        # settle move (settle.move_s): the feedback's reference; tau_c: the continuation's time (nan: none)
        ref_fb, tau_c = self._settle_move(dt, ref, x_meas_m, v_hat, ilc)
        settling = tau_c == tau_c
        if not (v_r == 0.0 and a_r == 0.0) and (self._sync_armed or (
                settling and self._sm.stiff and cfg.feedforward.rest_sync_on_start)):
            # a move starts after a standstill whose stop synchronisation was under way, or during a settle move
            # from ahead: the synchronisation completes here, before the model takes the move's first step
            # (_sync_on_start). The continuation's reversal spring force u_k, the plant's reversal there that the
            # model has not seen, goes to the observer first (as at the continuation's end, d̂ += u_k: no step in
            # u) and with it into the model; the continuation goes on for the feedback without it (kept, the model's
            # own reversal at the move's start came on top of it: a 10 ms dwell, 15 µm ahead)
            s_dir = v_r if v_r != 0.0 else a_r
            self._start_edge(dt, ff, dob, settling, 1.0 if s_dir > 0.0 else -1.0)  # type: ignore[arg-type]
        # feed-forward (advanced only by the part of dt that hold() has not covered)
        dt_ff = dt - self._ff_ahead_s
        self._ff_ahead_s = 0.0
        u_ff = (ff.step(dt_ff if dt_ff > 1e-9 * dt else dt, ref, self._ref_stop) * self.ff_scale
                if ff is not None else 0.0)
        if self._ff_bump is not None:  # feed-forward replaced by retune: Δ = old − new force is taken over by
            delta = self._ff_bump - u_ff  # the observer (its residual u − u_ff grows by Δ) or, without one, by
            self._ff_bump = None          # the integrator; either way u is continuous and nothing re-converges
            if dob is not None:
                dob.shift(delta)
                st.u_obs_prev_n += delta
            else:
                self.pid.preload(self.pid.state.u_pid_n + delta)
        ffc = cfg.feedforward
        if ffc.inertia:
            a_in = a_r
            last = self._last_ref
            if ffc.inertia_lookahead and last is not None:
                la = ff.lookahead_s if ff is not None else (
                    0.5 * dt if ffc.lookahead_s is None else ffc.lookahead_s)
                a_in += (a_in - last.a_m_s2) / dt * la  # a(t + τ_a) under constant jerk
            if settling:  # along the settle move: m·(a_r − c̈), with the same look-ahead
                a_in -= self._sm.sample(tau_c + (la if ffc.inertia_lookahead and last is not None else 0.0))[2]
            u_in = self._d_m_ff * a_in
        else:
            u_in = 0.0
        # observer (residual form: its input is the previous command minus the previous friction FF): one step of its
        # filter per sample, whatever the interval (QFilterDob, "Irregular sampling")
        d_hat = 0.0 if dob is None else dob.step(dt, x_meas_m, v_hat, st.u_obs_prev_n, a_r)
        if self._d_held:
            # the stiffness test's witness: the force the stage takes, u − m·a, through the observer's low-pass (an
            # observer on the whole command that nothing shifts: its ū and m·Δv̂ are centred on the last sample), and
            # the position at the last sample through the same low-pass
            hw = self._hw
            self._h_f = hw.step(dt, x_meas_m, v_hat, st.u_n, a_r)
            self._h_age_s += dt
            xm = st.x_prev_m if st.x_prev_m == st.x_prev_m else x_meas_m
            ah = hw._alpha
            self._h_xf = xm if self._h_xf != self._h_xf else ah * self._h_xf + (1.0 - ah) * xm
        at_rest = v_r == 0.0 and a_r == 0.0
        if at_rest:
            self._ev_dir = 0.0  # the next motion starts a new branch (_stuck_dob)
            self._x_rest_m = math.nan  # set again only by a move that starts with the spring loaded
        else:
            if self._d_stuck:
                d_hat = self._stuck_dob(dt, ref, x_meas_m, u_ff, d_hat, dob)  # type: ignore[arg-type]
            if self._s_rest != 0.0:
                # a move starts with the rest spring loaded: _rest_spring folds its force into the observer, which
                # carries it for a while; _adapt leaves it alone for the first adapt_presliding_m of travel
                self._x_rest_m = x_r
            elif abs(x_r - self._x_rest_m) >= ffc.adapt_presliding_m:
                self._x_rest_m = math.nan
        if at_rest:
            self._ad_run_s = -1.0  # (negative: the gate's filters restart with the next motion)
            self._gate_shut = False
        elif self._d_learn or self._d_adapt:
            # the learners' confidence gate: the observer's estimate is a model error only once the reference's
            # inertia force m·a_r has not moved by more than ADAPT_LAG_FRACTION of the model force (or its Coulomb
            # level) over the last observer time constant (against its low-pass at the observer's bandwidth) for
            # ADAPT_SETTLED_TIME_CONSTANTS of them in a row, and, after such an inertia transient, neither has the
            # stage's lag behind it through the friction's spring, θ·Σk·e; before, the estimate carries the move's
            # transient (acceleration, break-away, the stage's lag) and the observer's own lag. The lag alone does
            # not shut the gate: a wrong model's lag is its evidence.
            a = self._dob_decay(dt)
            th = self.ff_scale
            e_now = x_r - x_meas_m
            if self._ad_run_s < 0.0:  # first moving step: the filters start here, from a settled state (the
                # observer has settled at rest; a gentle start keeps the gate open, a fast one shuts it at once)
                self._gate_a, self._gate_e = 0.0, e_now
                self._ad_run_s = ADAPT_SETTLED_TIME_CONSTANTS / self._d_g
            self._gate_a = a * self._gate_a + (1.0 - a) * a_r
            self._gate_e = a * self._gate_e + (1.0 - a) * e_now
            lim = ADAPT_LAG_FRACTION * max(abs(u_ff) / th if th > 0.0 else 0.0,
                                           self._f_kin if self._f_kin == self._f_kin else 0.0)
            if self.mass_kg * abs(a_r - self._gate_a) > lim:
                self._gate_shut = True  # an inertia transient: the lag must settle too before the gate reopens
            quiet = not self._gate_shut or th * self._k_ps * abs(e_now - self._gate_e) <= lim
            if self.mass_kg * abs(a_r - self._gate_a) > lim or dt > IRREGULAR_DT_PERIODS * self.period_s:
                quiet = False
            self._ad_run_s = self._ad_run_s + dt if quiet else 0.0
            if self._ad_run_s * self._d_g >= ADAPT_SETTLED_TIME_CONSTANTS:
                self._gate_shut = False
        if self._d_adapt and not at_rest and isinstance(ff, FrictionFeedforward):
            # the stiffness evidence of a reversal (the adaptation): the model's branch starts at the reference's
            # turning point, the plant's at the stage's; if the stage was off the reference there by more than
            # ADAPT_LAG_FRACTION of the reversal's force through the friction's spring (θ·Σk·|e|: a move's
            # junction, the stage lagging on the soft side), the two branches differ by that spring force and the
            # stage rings on it, which the observer's estimate reads as a stiffness error: no β evidence then
            fst = ff.state
            if fst.x_rev_m != self._rev_x:
                self._rev_x = fst.x_rev_m
                lim = ADAPT_LAG_FRACTION * max(abs(fst.f_rev_n), self._f_kin if self._f_kin == self._f_kin else 0.0)
                self._rev_ok = self.ff_scale * self._k_ps * abs(x_r - x_meas_m) <= lim
        if self._d_learn:
            u_ff, d_hat = self._learn_moves(dt, ff, u_ff, d_hat, dob, at_rest, ilc,  # type: ignore[arg-type]
                                            x_r - x_meas_m)
        if self._d_adapt and not ilc and not at_rest:  # (_adapt changes nothing at rest)
            u_ff, d_hat = self._adapt(dt, ref, u_ff, d_hat, dob, at_rest)  # type: ignore[arg-type]
        # feedback + clamp
        pid = self.pid
        if self._d_spring:
            # while ILC takes part the spring stays released (folded into the observer, as at a move's start):
            # its load at each stop depends on where the previous repetition ended, so it would make the
            # repeated motion's error differ from one repetition to the next (ILC learns the stops too)
            d_hat = self._rest_spring(dt, ref, x_meas_m, d_hat, at_rest and not ilc and not settling,
                                      dob)  # type: ignore[arg-type]
        elif not at_rest:
            self._h_moved = True  # (a spring a retune switches on later judges its branches as after a move)
        if settling and self._sm.stiff:
            # settle move from ahead: the reversal's spring force along the continuation (the planned stage travel
            # e₀ − c, looked ahead by τ_a as the inertia term), outside the observer's input (module docstring)
            sm = self._sm
            if tau_c == 0.0:
                if self._ahead_pass == 2:  # the second: the first's gain × its planned / measured travel
                    self._k_ahead *= self._ahead_ratio
                    self._ahead_ks *= self._ahead_ratio
                    self._ahead_ratio = 1.0
                else:  # the first sample: the gain γ·θ·β·Σk (θ, β as the stop's learning left them), held
                    beta = ff.input_scale if isinstance(ff, FrictionFeedforward) else 1.0
                    th = self.ff_scale
                    self._k_ahead = cfg.settle.ahead_stiffness_fraction * th * beta * self._k_ps
                    self._ahead_ks = beta
                    self._ahead_fs = cfg.settle.ahead_stiffness_fraction * th
                    # the friction the feed-forward implies, θ·f_ff + u_k, stays within the model's range ±θ·ΣW_i
                    f_h = th * ff.state.f_friction_n if isinstance(ff, FrictionFeedforward) else 0.0
                    f_lim = th * self._f_max
                    self._u_k_lo, self._u_k_hi = -f_lim - f_h, f_lim - f_h
                    self._tau_a = ff.lookahead_s if ff is not None else 0.0
                    self._ahead_pass = 1
                    self._u_k_base = 0.0
            travel = sm.e0 - sm.sample(tau_c + self._tau_a)[0]
            if abs(travel) * self._ahead_ks <= self._rev_lin_m:  # the reversal's linear part: k·travel
                f_k = self._k_ahead * travel
            else:  # beyond it the elements slip: Masing's curve, at most the whole swing 2·ΣW_i
                f_k = self._ahead_fs * reversal_force(travel, self._ahead_ks, self._rev_el)
            self._u_k = min(self._u_k_hi, max(self._u_k_lo, self._u_k_base + f_k))
        elif self._u_k != 0.0:
            # the continuation is over: its held force goes to the observer (d̂ += u_k: no step in u)
            dob.shift(self._u_k)  # type: ignore[union-attr]
            d_hat += self._u_k
            self._u_k = 0.0
            self._ahead_pass = 0
        if self._d_rest_int:
            if at_rest and not settling and not ilc:
                d_hat = self._rest_integral(dt, x_r - x_meas_m, v_hat, d_hat)
            elif (self._ri_n != 0.0 or self._ri_still_s != 0.0 or self._ri_off or self._ri_swings or self._ri_side
                  or self._ri_v != 0.0):
                self._reset_rest_integral()  # the reference moves: the next standstill starts afresh
        self._sync_armed = False
        if self._d_creep:  # (from the end of the commanded move: a settle move's travel back is a reversal)
            self._sync_creep(dt, at_rest, x_meas_m, ff.latch.direction, d_hat)  # type: ignore[union-attr]
        elif self._cr_n:  # the gate off (a retune turned the learning from moves on): none left standing
            self._cr_n = 0
        if (at_rest and not settling and self._d_sync
                and self._rest_sync_where(ff, x_r, x_meas_m, v_hat)):  # type: ignore[arg-type]
            u_ff, d_hat = self._rest_sync(dt, ff, u_ff, d_hat, dob)  # type: ignore[arg-type]
            self._sync_armed = ffc.rest_sync_on_start
        if (at_rest and not settling and self._d_ri_sync
                and self._rest_sync_where(ff, x_r, x_meas_m, v_hat)):  # type: ignore[arg-type]
            u_ff = self._rest_sync_integral(dt, ff, u_ff)  # type: ignore[arg-type]
            self._sync_armed = ffc.rest_sync_on_start
        hold = at_rest and not settling and self._d_hold
        if self._d_rest_gains:
            # the rest gains act while the stage is held (stuck): entered after REST_GAINS_DWELL_S with
            # |v̂| <= REST_GAINS_ENTER_M_S, left at once when |v̂| > REST_GAINS_EXIT_M_S (it slips) or the
            # reference moves
            if not (at_rest and not settling) or abs(v_hat) > REST_GAINS_EXIT_M_S:
                self._rg_still_s = 0.0
                want = False
            else:
                self._rg_still_s = self._rg_still_s + dt if abs(v_hat) <= REST_GAINS_ENTER_M_S else 0.0
                want = self._rest_gains or self._rg_still_s >= REST_GAINS_DWELL_S
            if want != self._rest_gains:
                self._set_rest_gains(want)
        pid.hold_integrator = hold
        if hold:
            ps = pid.state
            i_n = ps.i_n
            if i_n != 0.0:
                # hand the integral term to the observer (d̂ += I, I = 0: no step in u at the hand-over; the
                # observer then carries the whole steady force); a held non-zero I would stand against P and
                # leave a steady error e = −I/K_p
                dob.shift(i_n)  # type: ignore[union-attr]
                d_hat += i_n
                ps.i_n = 0.0
        u = pid.step(dt, ref_fb[0], x_meas_m, ref_fb[1], u_ff + u_in + d_hat + u_learn_n + self._u_k,
                     self._u_lim)
        ps = pid.state
        in_pos = self.settle.step(dt, x_r - x_meas_m, at_rest)
        st.u_next_n = predict_next_force(u, u_ff + u_in + u_learn_n,
                                         st.u_ff_n + st.u_inertia_n + self._u_learn, dt, self.period_s,
                                         self._u_lim)
        st.x_prev_m = x_meas_m
        st.v_hat_m_s = v_hat
        st.u_n = u
        st.u_ff_n = u_ff
        st.u_inertia_n = u_in
        st.d_hat_n = d_hat
        st.u_obs_prev_n = u - u_ff - self._u_k
        st.steps += 1
        self._last_ref = ref
        self._u_learn = u_learn_n
        terms = {"u_pid": ps.u_pid_n, "u_p": ps.p_n, "u_i": ps.i_n, "u_d": ps.d_n, "u_dob": d_hat, "u_ff": u_ff,
                 "u_inertia": u_in, "in_position": 1.0 if in_pos else 0.0}
        st.terms = terms
        if ps.saturated:
            limited: tuple[str, ...] = ("force", "anti_windup") if not ps.integrating else ("force",)
        elif not ps.integrating and not hold:
            limited = ("anti_windup",)
        else:
            limited = ()
        return Command(u, terms, limited)


    def hold(self, dt: float, ref: Reference, u_learn_n: float = 0.0) -> Command:
        """A cycle without a new sample (stale: late or dropped frame; real-time safe). ``dt`` [s]: the time
        since the previous cycle (stepped or held); ``u_learn_n`` [N]: the learned feed-forward (ILC).

        The first ``stale_predict_cycles`` stale cycles in a row are stepped on a predicted position: the
        stage is taken to keep its last measured tracking error e, x̂ = x_r(t) − e. PID, observer, velocity
        estimate and feed-forward then advance at the loop's own rate, so a single late or dropped sample
        neither holds a fast observer for a period nor hands it an interval of 2T (the 10 µm cosine's error
        grew 2.4x with 10 % late TPDOs when the observer and the velocity estimate skipped the sample; with
        the prediction the error stays at the clean run's). The next fresh sample corrects the prediction.

        Later stale cycles hold the feedback terms (u_pid, d̂) at their last values: nothing integrates, no
        estimate moves. The feed-forward follows the reference (it needs no measurement): the friction model is
        advanced by ``dt`` (the next :meth:`step` advances it only by the rest of its own dt) and the inertia
        term is m·a_ref. The force is limited to the stale-data band (hold or slow down, never run away)::

            u = clamp( u_pid,held + d̂_held + u_ff(ref) + m_ff·a_ref + u_l , ±F_L )   (F_L: force_limit_n)
            u = clamp( u, m_ff·a_ref + u_l ± L ),   L = max(θ·F_c or stale_force_limit_n, |u_ff(ref)|)

        A feedback force built up before the gap (a break-away, a disturbance) is not held blind: a sliding
        stage feels at least the Coulomb level F_c (Stribeck and viscous friction only add), and a stuck one
        needs the static level to break away, so with |u − m·a_ref| ≤ F_c the stage does not accelerate
        beyond the reference; |u_ff| (pre-sliding up to the static level, the sliding friction at the
        reference's speed) is what following the reference needs. The limited force is held from then on.
        """
        check_dt(dt)
        st = self.state
        if (self._gap < self.cfg.stale_predict_cycles and math.isfinite(self._e_last)
                and self._pending is None and self._ff_ahead_s == 0.0):
            self._gap += 1
            cmd = self._step(dt, ref.x_m - self._e_last, ref, u_learn_n, self._learn_active or u_learn_n != 0.0)
            self._pred_s += dt
            return Command(cmd.force_n, cmd.terms, ("stale", "predicted") + cmd.limited)
        self._gap += 1
        ff = self.ff
        ffc = self.cfg.feedforward
        if ff is None or self._ff_bump is not None or self._pending is not None:
            return Command(st.u_n, st.terms, ("stale",))
        settling = self._sm.active  # (a held cycle does not advance the continuation: the feedback is held)
        if (not (ref.v_m_s == 0.0 and ref.a_m_s2 == 0.0) and isinstance(ff, FrictionFeedforward)
                and (self._sync_armed or (settling and self._sm.stiff and ffc.rest_sync_on_start))):
            # a move starts on a blind cycle: the start-edge sync (and the hand-over of a settle move from ahead's
            # reversal force) before the model's first step, as in _step
            s_dir = ref.v_m_s if ref.v_m_s != 0.0 else ref.a_m_s2
            self._start_edge(dt, ff, self.dob, settling, 1.0 if s_dir > 0.0 else -1.0)
        u_ff = ff.step(dt, ref, self._ref_stop) * self.ff_scale
        self._ff_ahead_s += dt
        m_ff = ffc.mass_kg if ffc.mass_kg is not None else self.mass_kg
        u_in = m_ff * ref.a_m_s2 if ffc.inertia else 0.0
        u_fb = st.u_n - st.u_ff_n - st.u_inertia_n - self._u_learn
        lim = self._u_lim
        u = max(-lim, min(lim, u_fb + u_ff + u_in + u_learn_n))
        st.u_next_n = predict_next_force(u, u_ff + u_in + u_learn_n, st.u_ff_n + st.u_inertia_n + self._u_learn,
                                         dt, self.period_s, lim)
        self._u_learn = u_learn_n
        st.u_n = u
        st.u_ff_n = u_ff
        st.u_inertia_n = u_in
        st.u_obs_prev_n = u - u_ff - self._u_k  # (the held command keeps the continuation's force: not observed)
        terms = dict(st.terms)
        terms["u_ff"] = u_ff
        terms["u_inertia"] = u_in
        st.terms = terms
        return self._stale_limit(u, terms)


def _kinetic_level(ff: FrictionFeedforward | CoulombFeedforward | None) -> float:
    """The friction feed-forward's Coulomb (kinetic) level F_c [N]: ``coulomb_n``, the model's ``fc_n``, else
    its total slip force (``fs_n`` or Σ ``w_n``, a model without a Stribeck dip); nan without one."""
    if isinstance(ff, CoulombFeedforward):
        return float(ff.coulomb_n) if ff.coulomb_n > 0.0 else math.nan
    if not isinstance(ff, FrictionFeedforward):
        return math.nan
    q = getattr(ff.model, "params", None)
    for name in ("fc_n", "fs_n"):
        v = getattr(q, name, None)
        if isinstance(v, (int, float)) and v > 0.0:
            return float(v)
    w = getattr(q, "w_n", None)
    if isinstance(w, tuple) and w:
        return float(sum(w))
    return math.nan


def _break_gain(ff: FrictionFeedforward | CoulombFeedforward | None, k_ps: float, f_kin: float,
                range_m: float) -> float:
    """The rest integral's gain on the soft side [N/m] (a stage stopped behind its target, stuck at its break-away
    level): k_b = min(Σk, ΔF_b/r), ΔF_b = max(F_s − F_c, REST_INTEGRAL_GAP_MIN·F_c) from the model's ``fs_n`` and
    F_c (:func:`_kinetic_level`), r = ``rest_spring_range_m``; 0 without a model's stiffness or Coulomb level."""
    if not isinstance(ff, FrictionFeedforward) or k_ps <= 0.0 or not f_kin > 0.0 or range_m <= 0.0:
        return 0.0
    fs = getattr(getattr(ff.model, "params", None), "fs_n", None)
    gap = float(fs) - f_kin if isinstance(fs, (int, float)) else 0.0
    return min(k_ps, max(gap, REST_INTEGRAL_GAP_MIN * f_kin) / range_m)


def _reversal_elements(ff: FrictionFeedforward | CoulombFeedforward | None
                       ) -> tuple[tuple[tuple[float, float], ...], float, float]:
    """The model's friction as elasto-slip elements for the settle move from ahead's force bound: ((k_i [N/m],
    2·W_i [N]), ...), the largest friction force ΣW_i [N] and the travel min 2·W_i/k_i [m] up to which the
    reversal is linear (:func:`stagectl.control.settle_move.reversal_force`). GMS: W_i = α_i·max(F_s, F_c);
    Maxwell slip: its W_i; another model with a stiffness and a friction level (LuGre, Dahl, Hsieh): one element
    (Σk, max(F_s, F_c)). ((), inf, inf) when not known: no bound."""
    none: tuple[tuple[tuple[float, float], ...], float, float] = ((), math.inf, math.inf)
    if not isinstance(ff, FrictionFeedforward):
        return none
    q = getattr(ff.model, "params", None)
    ks = getattr(q, "k_n_m", None)
    ws: Any = None
    if isinstance(ks, tuple):
        w = getattr(q, "slip_forces_n", None)
        alpha = getattr(q, "alpha", None)
        levels = [v for v in (getattr(q, "fs_n", None), getattr(q, "fc_n", None)) if isinstance(v, (int, float))]
        if isinstance(w, tuple):
            ws = w
        elif isinstance(alpha, tuple) and levels:
            ws = tuple(a * max(levels) for a in alpha)
    else:
        k = _stiffness(ff)
        levels = [v for v in (getattr(q, "fs_n", None), getattr(q, "fc_n", None)) if isinstance(v, (int, float))]
        if k > 0.0 and levels:
            ks, ws = (k,), (max(levels),)
    if not (isinstance(ks, tuple) and isinstance(ws, tuple) and len(ks) == len(ws) and ks
            and all(k > 0.0 and w > 0.0 for k, w in zip(ks, ws))):
        return none
    el = tuple((float(k), 2.0 * float(w)) for k, w in zip(ks, ws))
    return el, 0.5 * sum(w2 for _, w2 in el), min(w2 / k for k, w2 in el)


def _stiffness(ff: FrictionFeedforward | CoulombFeedforward | None) -> float:
    """Initial pre-sliding stiffness Σk [N/m] of a model feed-forward's friction model (0: none / not known)."""
    if not isinstance(ff, FrictionFeedforward):
        return 0.0
    k = getattr(ff.model, "stiffness_n_m", None)
    return float(k) if isinstance(k, (int, float)) and k > 0.0 else 0.0


def _scaled_pid(p: PidConfig, s: float) -> PidConfig:
    """PID gains for a crossover divided by ``s`` (Kp/s², Ki/s³, Kd/s, fc/s)."""
    if s == 1.0:
        return p
    return dataclasses.replace(p, kp_n_m=p.kp_n_m / s**2, ki_n_m_s=p.ki_n_m_s / s**3, kd_n_s_m=p.kd_n_s_m / s,
                               derivative_cutoff_hz=p.derivative_cutoff_hz / s)


def _scaled_dob(d: DobConfig, s: float) -> DobConfig:
    return d if s == 1.0 else dataclasses.replace(d, bandwidth_hz=d.bandwidth_hz / s)


def controller_from_mapping(data: Any, timing: Timing | float,
                            model: StageModel | FrictionModel | None = None) -> StageController:
    """Convenience: ``controller:`` YAML mapping (no ``model_file``) -> :class:`StageController` (errors as
    ConfigError)."""
    return StageController(load(ControllerConfig, data, "controller"), timing, model)


__all__ = [
    "FORCE_TERM_NAMES",
    "TERM_NAMES",
    "SettleConfig",
    "ControllerConfig",
    "ControllerState",
    "DobConfig",
    "FF_LIVE_KEYS",
    "FeedforwardConfig",
    "PidConfig",
    "StageController",
    "check_controller",
    "controller_from_mapping",
    "controller_mass",
    "resolve_model",
    "same_friction_ff",
]
