/* The extension service._kernel: registers the compiled core (core/kernel.c), the daemon's tick writer
 * (daemon/tickwriter.c), the plant's integrator (plant/rk4.c) and the network's (plant/network.c). */
#include "kernel.h"

static PyMethodDef module_methods[] = {
    {"plant_steps", (PyCFunction)(void (*)(void))plant_steps, METH_FASTCALL, "RLCPlant.advance's RK4 loop"},
    {"network_steps", (PyCFunction)(void (*)(void))network_steps, METH_FASTCALL,
     "service/plant/network.py steps(): RK4 steps of a DC network in node/branch form"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef kernel_module = {.m_base = PyModuleDef_HEAD_INIT, .m_name = "service._kernel",
                                           .m_doc = "Compiled twin of the control core's step and the plant's "
                                                    "integrator.", .m_size = -1, .m_methods = module_methods};

PyMODINIT_FUNC PyInit__kernel(void)
{
    if (PyType_Ready(&KernelType) < 0 || PyType_Ready(&TickWriterType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&kernel_module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&KernelType);
    if (PyModule_AddObject(m, "Kernel", (PyObject *)&KernelType) < 0) {
        Py_DECREF(&KernelType);
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&TickWriterType);
    if (PyModule_AddObject(m, "TickWriter", (PyObject *)&TickWriterType) < 0) {
        Py_DECREF(&TickWriterType);
        Py_DECREF(m);
        return NULL;
    }
    if (PyModule_AddIntConstant(m, "OUT_LEN", O_N) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
