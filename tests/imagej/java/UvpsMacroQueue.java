// A user's ImageJ session for tests and screenshots (tests/imagej/gui_session.py): starts ImageJ
// normally (windows, Log window, dialogs; no -batch) and runs the macro files a test drops into the
// folder given by -Duvps.queue.dir, one after the other, the way Plugins > Macros > Run does (from a
// thread of its own, IJ.runMacroFile). After NAME.ijm it writes NAME.done (holding the status bar's text), so
// the test knows the step is over and what the status bar said; meanwhile the test answers dialogs with xdotool as a user would.
import ij.IJ;
import ij.ImageJ;

import java.io.File;
import java.io.FileOutputStream;
import java.util.Arrays;

public class UvpsMacroQueue {

    public static void main(String[] args) throws Exception {
        final File dir = new File(System.getProperty("uvps.queue.dir"));
        ImageJ.main(args);
        Thread watcher = new Thread(new Runnable() {
            public void run() {
                watch(dir);
            }
        }, "uvps macro queue");
        watcher.setDaemon(true);
        watcher.start();
    }

    private static void watch(File dir) {
        while (true) {
            File[] files = dir.listFiles();
            if (files != null) {
                Arrays.sort(files);
                for (File f : files) {
                    String name = f.getName();
                    if (!name.endsWith(".ijm")) {
                        continue;
                    }
                    File done = new File(dir, name.substring(0, name.length() - 4) + ".done");
                    if (done.exists()) {
                        continue;
                    }
                    runOne(f);
                    try {
                        // the status bar as the step left it ("uvps: ... cancelled")
                        String status = ij.ImageJ.getStatusBarText();
                        FileOutputStream out = new FileOutputStream(done);
                        out.write((status == null ? "" : status).getBytes("UTF-8"));
                        out.close();
                    } catch (Exception e) {
                        System.err.println("UVPS-QUEUE: cannot write " + done + ": " + e);
                    }
                }
            }
            try {
                Thread.sleep(100);
            } catch (InterruptedException e) {
                return;
            }
        }
    }

    private static void runOne(final File macro) {
        // Plugins > Macros > Run runs the file on a command thread (named after the command)
        Thread t = new Thread(new Runnable() {
            public void run() {
                IJ.runMacroFile(macro.getAbsolutePath(), "");
            }
        }, "Run$_Run...");
        t.start();
        try {
            t.join();
        } catch (InterruptedException e) {
            return;
        }
    }
}
