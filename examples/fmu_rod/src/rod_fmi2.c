/* FMI 2.0 interface of the example rod (Model Exchange and Co-Simulation in one binary).
 * Physics in rod_model.h. Built by ../build_fmu.py against the FMI 2.0 headers fmpy ships.
 * The FMU state (get/set/serialize) is the RodState struct; no globals, any number of instances. */
#include <stdio.h>
#include <stdlib.h>
#include "fmi2Functions.h"
#include "rod_model.h"

#ifndef MODEL_GUID
#define MODEL_GUID "{sep-rod}"
#endif
#ifndef N_EVENT_INDICATORS
#define N_EVENT_INDICATORS 0
#endif

typedef struct {
    RodState s;
    RodDerived d;
    double dT[N_NODES];
    int dT_valid;
    fmi2Type type;
    fmi2CallbackFunctions cb;
} Instance;

static fmi2Status fail(Instance *c, const char *msg) {
    if (c && c->cb.logger) c->cb.logger(c->cb.componentEnvironment, "rod", fmi2Error, "error", msg);
    return fmi2Error;
}

static void refresh(Instance *c) {
    if (!c->dT_valid) { rod_rhs(&c->s, &c->d, c->s.T, c->dT); c->dT_valid = 1; }
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cat[]) {
    (void)c; (void)on; (void)n; (void)cat; return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String resources,
                              const fmi2CallbackFunctions *cb, fmi2Boolean visible, fmi2Boolean logging) {
    (void)name; (void)resources; (void)visible; (void)logging;
    if (!cb || !cb->allocateMemory || !cb->freeMemory || !guid || strcmp(guid, MODEL_GUID) != 0) return NULL;
    Instance *c = (Instance *)cb->allocateMemory(1, sizeof(Instance));
    if (!c) return NULL;
    c->cb = *cb;
    c->type = type;
    rod_defaults(&c->s);
    rod_derive(&c->s, &c->d);
    rod_init_states(&c->s);
    return c;
}

void fmi2FreeInstance(fmi2Component c) {
    Instance *i = (Instance *)c;
    if (i) i->cb.freeMemory(i);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDef, fmi2Real tol, fmi2Real start,
                               fmi2Boolean stopDef, fmi2Real stop) {
    (void)tolDef; (void)tol; (void)stopDef; (void)stop;
    ((Instance *)c)->s.time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Instance *i = (Instance *)c;
    if (i->s.n_substeps < 1) return fail(i, "n_substeps must be >= 1");
    if (!(i->s.p[P_LENGTH] > 0) || !(i->s.p[P_SIGMA] > 0) || !(i->s.p[P_TSCALE] > 0))
        return fail(i, "length, heater_sigma and t_scale must be > 0");
    rod_derive(&i->s, &i->d);
    rod_init_states(&i->s);
    i->s.initialized = 1;
    i->dT_valid = 0;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2Reset(fmi2Component c) {
    Instance *i = (Instance *)c;
    rod_defaults(&i->s);
    rod_derive(&i->s, &i->d);
    rod_init_states(&i->s);
    i->dT_valid = 0;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real value[]) {
    Instance *i = (Instance *)c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] >= VR_DER && vr[k] < VR_U) refresh(i);
        if (!rod_get_real(&i->s, &i->d, i->dT, vr[k], &value[k])) return fail(i, "fmi2GetReal: unknown value reference");
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[]) {
    Instance *i = (Instance *)c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] != VR_NSUB) return fail(i, "fmi2GetInteger: unknown value reference");
        value[k] = i->s.n_substeps;
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Boolean value[]) {
    (void)vr; (void)value; return nvr ? fail((Instance *)c, "no Boolean variables") : fmi2OK;
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2String value[]) {
    (void)vr; (void)value; return nvr ? fail((Instance *)c, "no String variables") : fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real value[]) {
    Instance *i = (Instance *)c;
    for (size_t k = 0; k < nvr; k++)
        if (!rod_set_real(&i->s, vr[k], value[k])) return fail(i, "fmi2SetReal: not settable now");
    i->dT_valid = 0;
    return fmi2OK;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer value[]) {
    Instance *i = (Instance *)c;
    for (size_t k = 0; k < nvr; k++) {
        if (vr[k] != VR_NSUB || i->s.initialized) return fail(i, "fmi2SetInteger: not settable now");
        i->s.n_substeps = value[k];
    }
    return fmi2OK;
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Boolean value[]) {
    (void)vr; (void)value; return nvr ? fail((Instance *)c, "no Boolean variables") : fmi2OK;
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2String value[]) {
    (void)vr; (void)value; return nvr ? fail((Instance *)c, "no String variables") : fmi2OK;
}

/* ---------------------------------------------------------------- FMU state */
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *state) {
    Instance *i = (Instance *)c;
    if (!*state) *state = i->cb.allocateMemory(1, sizeof(RodState));
    if (!*state) return fail(i, "out of memory");
    memcpy(*state, &i->s, sizeof(RodState));
    return fmi2OK;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate state) {
    Instance *i = (Instance *)c;
    if (!state) return fail(i, "fmi2SetFMUstate: no state");
    memcpy(&i->s, state, sizeof(RodState));
    rod_derive(&i->s, &i->d);
    i->dT_valid = 0;
    return fmi2OK;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *state) {
    Instance *i = (Instance *)c;
    if (state && *state) { i->cb.freeMemory(*state); *state = NULL; }
    return fmi2OK;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate state, size_t *size) {
    (void)c; (void)state; *size = sizeof(RodState); return fmi2OK;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate state, fmi2Byte bytes[], size_t size) {
    if (size != sizeof(RodState)) return fail((Instance *)c, "fmi2SerializeFMUstate: wrong size");
    memcpy(bytes, state, sizeof(RodState));
    return fmi2OK;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte bytes[], size_t size, fmi2FMUstate *state) {
    Instance *i = (Instance *)c;
    if (size != sizeof(RodState)) return fail(i, "fmi2DeSerializeFMUstate: wrong size");
    if (!*state) *state = i->cb.allocateMemory(1, sizeof(RodState));
    if (!*state) return fail(i, "out of memory");
    memcpy(*state, bytes, sizeof(RodState));
    return fmi2OK;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real dz[],
                                        fmi2Real du[]) {
    (void)u; (void)nu; (void)z; (void)nz; (void)dz; (void)du;
    return fail((Instance *)c, "directional derivatives are not provided");
}

/* ---------------------------------------------------------------- Model Exchange */
fmi2Status fmi2EnterEventMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo *e) {
    (void)c;
    memset(e, 0, sizeof(*e));
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSet, fmi2Boolean *enter, fmi2Boolean *term) {
    (void)c; (void)noSet; *enter = fmi2False; *term = fmi2False; return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real t) { ((Instance *)c)->s.time = t; return fmi2OK; }

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    Instance *i = (Instance *)c;
    if (nx != N_NODES) return fail(i, "fmi2SetContinuousStates: wrong number of states");
    memcpy(i->s.T, x, sizeof(double) * N_NODES);
    i->dT_valid = 0;
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t nx) {
    Instance *i = (Instance *)c;
    if (nx != N_NODES) return fail(i, "fmi2GetDerivatives: wrong number of states");
    rod_rhs(&i->s, &i->d, i->s.T, dx);
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t nz) {
    Instance *i = (Instance *)c;
    for (size_t k = 0; k < nz; k++) z[k] = i->s.T[0] - 200.0;   /* only declared by a test variant */
    return fmi2OK;
}

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    Instance *i = (Instance *)c;
    if (nx != N_NODES) return fail(i, "fmi2GetContinuousStates: wrong number of states");
    memcpy(x, i->s.T, sizeof(double) * N_NODES);
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    (void)c; for (size_t k = 0; k < nx; k++) x[k] = 100.0; return fmi2OK;
}

/* ---------------------------------------------------------------- Co-Simulation */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    return fail((Instance *)c, "input derivatives are not supported");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                        const fmi2Integer order[], fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    return fail((Instance *)c, "output derivatives are not supported");
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSet) {
    Instance *i = (Instance *)c;
    (void)noSet;
    if (fabs(t - i->s.time) > 1e-9 * (1.0 + fabs(t))) return fail(i, "fmi2DoStep: time differs from the FMU's");
    if (!(h > 0)) return fail(i, "fmi2DoStep: step size must be > 0");
    rod_rk4(&i->s, &i->d, h);
    i->dT_valid = 0;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind k, fmi2Status *v) {
    (void)c; (void)k; *v = fmi2OK; return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind k, fmi2Real *v) {
    Instance *i = (Instance *)c;
    if (k != fmi2LastSuccessfulTime) return fmi2Discard;
    *v = i->s.time; return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind k, fmi2Integer *v) {
    (void)c; (void)k; (void)v; return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind k, fmi2Boolean *v) {
    (void)c; (void)k; *v = fmi2False; return fmi2Discard;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind k, fmi2String *v) {
    (void)c; (void)k; (void)v; return fmi2Discard;
}
