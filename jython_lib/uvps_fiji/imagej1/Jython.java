// The "Jython" plugin that plain ImageJ 1.x looks up (IJ.runPlugIn("Jython", "")) to run .py menu
// commands and scripts; Fiji ships its own, Debian's imagej does not (without it ImageJ opens a
// modal "download Jython?" dialog, which hangs offline and in -batch runs). scripts/install_fiji.py
// compiles it into <ImageJ>/plugins/jars/uvps_jython_interpreter.jar beside a copy of jython.jar;
// the real-ImageJ tests compile it onto their classpath. Macro_Runner.runPython(script, arg) passes the
// file's text; the path comes from Macro_Runner.getFilePath().
//
// Each run gets a fresh org.python.util.PythonInterpreter with sys.argv = [path, arg], __file__ and
// __name__ = "__main__". Python output goes to the JVM's stdout/stderr.
// Uncaught Python exceptions: normally logged to ImageJ's Log window (as Fiji does); with
// -Duvps.test=1 the traceback is printed to stderr after the marker line
// "UVPS-TEST: uncaught Python exception" and the JVM halts with status 4 (PYTHON_EXCEPTION_STATUS),
// so that a failing plugin cannot look like success in tests.
import ij.IJ;
import ij.plugin.Macro_Runner;
import ij.plugin.PlugInInterpreter;

import org.python.core.Py;
import org.python.core.PyException;
import org.python.core.PyList;
import org.python.core.PyString;
import org.python.core.PySystemState;
import org.python.util.PythonInterpreter;

public class Jython extends PlugInInterpreter {

    /** JVM exit status used in test mode for an uncaught Python exception. */
    public static final int PYTHON_EXCEPTION_STATUS = 4;

    private String returnValue = "";

    /** Called by IJ.runPlugIn("Jython", "") only to instantiate the interpreter. */
    @Override
    public void run(String arg) {
    }

    @Override
    public String run(String script, String arg) {
        returnValue = "";
        String path = Macro_Runner.getFilePath();
        if (path == null || !path.endsWith(".py")) {
            path = "<script>";
        }
        PySystemState state = new PySystemState();
        PyList argv = new PyList();
        argv.append(new PyString(path));
        argv.append(new PyString(arg == null ? "" : arg));
        state.argv = argv;
        state.dont_write_bytecode = true;
        PythonInterpreter py = new PythonInterpreter(null, state);
        try {
            py.setOut(System.out);
            py.setErr(System.err);
            py.set("__name__", new PyString("__main__"));
            py.set("__file__", new PyString(path));
            py.exec(py.compile(script, path));
        } catch (PyException e) {
            if (e.match(Py.SystemExit)) {
                // sys.exit() inside a plugin: ends the script, not ImageJ.
                returnValue = "";
            } else {
                report(path, e);
            }
        } catch (RuntimeException e) {
            report(path, e);
        } catch (ThreadDeath e) {
            report(path, e);
        } finally {
            py.cleanup();
        }
        return null;
    }

    /** A cancel, not a failure: ImageJ stopping the macro thread (Esc: ThreadDeath) or aborting
     *  a macro ("Macro canceled", thrown by a cancelled dialog or IJ.error in a macro). */
    static boolean isCancel(Throwable e) {
        for (int depth = 0; e != null && depth < 10; depth++) {
            if (e instanceof ThreadDeath || e instanceof InterruptedException) {
                return true;
            }
            String message = e.getMessage();
            if (message != null && message.contains(ij.Macro.MACRO_CANCELED)) {
                return true;
            }
            if (e instanceof PyException) {
                Object value = ((PyException) e).value.__tojava__(Throwable.class);
                if (value instanceof Throwable && value != e) {
                    e = (Throwable) value;
                    continue;
                }
                String text = e.toString();
                if (text.contains(ij.Macro.MACRO_CANCELED) || text.contains("ThreadDeath")) {
                    return true;
                }
            }
            e = e.getCause();
        }
        return false;
    }

    private static void report(String path, Throwable e) {
        if (isCancel(e)) {
            // what a user did on purpose: no stack trace (the menu item logged "cancelled")
            IJ.showStatus("cancelled");
            return;
        }
        if (System.getProperty("uvps.test") != null) {
            System.out.flush();
            System.err.println("UVPS-TEST: uncaught Python exception in " + path);
            System.err.println(e.toString());
            System.err.flush();
            Runtime.getRuntime().halt(PYTHON_EXCEPTION_STATUS);
        }
        IJ.log("Python exception in " + path + ":\n" + e.toString());
    }

    @Override
    public String getReturnValue() {
        return returnValue;
    }

    @Override
    public String getName() {
        return "Python";
    }

    @Override
    public String getImports() {
        return "from ij import IJ\n";
    }

    @Override
    public String getVersion() {
        return "2.7";
    }
}
